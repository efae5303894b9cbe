"""Run one small-preset simulation on the ranks of mpirun and save float64 strains (rank 0).

Usage: mpirun -n 2 python tests/mpi_simulate.py MESH_DIR OUT.npy [OBSERVABLE]
"""

import sys

import numpy as np
from mpi4py import MPI

from skinfem.config import load_config
from skinfem.model import SkinModel
from skinfem.params import Design, SkinParams

config = load_config("small")
if len(sys.argv) > 3:
    config = config.with_changes(observable={"kind": sys.argv[3]})
model = SkinModel(config, MPI.COMM_WORLD, mesh_dir=sys.argv[1])
frames = model.simulate(SkinParams(1.2e-3, 0.017, 12.0, 0.28, 30.0), Design(0.05, -0.05))
if MPI.COMM_WORLD.rank == 0:
    np.save(sys.argv[2], np.concatenate([frames.xy.ravel(), frames.strain.ravel()]))
