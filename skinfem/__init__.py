"""skinfem — finite-element forward model of skin actuated by a bonded active membrane.

Units: mm, MPa, N. Angles are degrees in files and on the command line, radians inside code.
Axes: x = alpha11 direction, y = alpha22 direction, z up; skin top at z = 0, block centred
at x = y = 0.

Modules that need DOLFINx (``mesh`` reading, ``materials``, ``model``, ``strain``) import it
lazily, so ``skinfem.config`` and ``skinfem.params`` work without FEniCSx.
"""

__version__ = "0.1.0"
