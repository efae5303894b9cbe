"""Import DOLFINx and PETSc the same way everywhere.

The PyPI wheel ``dolfinx-solver-real`` ships PETSc/MPICH libraries that must be loaded by
``import dolfinx_solver`` before ``dolfinx`` or ``petsc4py``. A conda-forge or apt DOLFINx
has no such module, and then the import is simply skipped.

PETSc's default ``VecMDot`` (BLAS ``gemv`` over GMRES's Krylov basis) sums in an order that
depends on where the vectors land in memory, so GMRES results — and with them Newton
iteration counts near the tolerance — changed from run to run in the last bits. The unrolled
kernels are deterministic; they are selected here (unless the user set the options) before
any vector exists, because PETSc reads them when a vector is created.

``JIT_OPTIONS`` compile the generated element kernels with ``-fassociative-math``: letting
the C compiler reorder the sums of FFCx's quadrature loops vectorises them and halves the
Jacobian assembly time (hyperelastic tangents on hexahedra); NaN/Inf semantics are kept (no
``-ffast-math``), and a given compiled kernel is still deterministic.
"""

from __future__ import annotations

try:  # the PyPI wheel; absent for conda/apt installs
    import dolfinx_solver  # noqa: F401
except ImportError:
    pass

try:
    import dolfinx  # noqa: F401
    import dolfinx.fem  # noqa: F401
    import dolfinx.fem.petsc  # noqa: F401
    import dolfinx.io  # noqa: F401
    import dolfinx.mesh  # noqa: F401
    import ufl  # noqa: F401
    from petsc4py import PETSc  # noqa: F401
except ImportError as exc:  # pragma: no cover - depends on the install
    raise ImportError(
        "skinfem needs DOLFINx 0.11 (FEniCSx). Install it with `pip install dolfinx-solver-real` "
        "or from conda-forge (`conda install -c conda-forge fenics-dolfinx`); see README 'Install'."
    ) from exc

_options = PETSc.Options()
for _name in ("vec_mdot_use_gemv", "vec_maxpy_use_gemv"):
    if not _options.hasName(_name):
        _options[_name] = False

JIT_OPTIONS = {
    "cffi_extra_compile_args": ["-O2", "-g0", "-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math"]
}

__all__ = ["dolfinx", "ufl", "PETSc", "JIT_OPTIONS"]
