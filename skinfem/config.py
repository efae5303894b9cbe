"""Typed, validated configuration of a skinid model and sweep (TOML).

A configuration is read from a TOML file or named after a built-in preset
(``skinfem/presets/<name>.toml``: ``small``, ``study``, ``paper``, ``check``, ``converged``). Every key is checked on
load; a wrong or unknown key raises :class:`ConfigError` with the key's dotted name.

Units: lengths in mm, moduli in MPa, angles in degrees (converted to radians in code).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

PRESET_DIR = Path(__file__).parent / "presets"
PARAM_NAMES = ("mu", "k1", "k2", "kappa", "theta")
N_SKIN = len(PARAM_NAMES)  # the skin parameters lead every parameter vector, in this order
THETA = PARAM_NAMES.index("theta")  # index of the fiber angle [deg] in parameter vectors
PARAM_UNITS = ("MPa", "MPa", "-", "-", "deg")


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range."""


def _check(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"config key '{key}': {message}")


MAX_EDGE_GROWTH = 4.0  # largest growth factor of edge-graded cells (mesh.edge_growth)


@dataclass(frozen=True)
class MeshConfig:
    """Geometry and resolution of the layered block (mm).

    The in-plane grid is a tensor product: uniform cells of ``h_membrane`` under the
    membrane footprint, geometrically graded to about ``h_far`` at the block edge. With
    0 < ``h_edge`` < ``h_membrane`` the cells at the membrane's edge are ``h_edge`` instead,
    graded geometrically to ``h_membrane`` at the centre and to ``h_far`` at the block edge
    (the strain concentrates at the edge; 0 or ``h_membrane``: no edge refinement).
    ``edge_growth`` says how: 0 (default), one progression on each side whose last cell is
    closest to ``h_membrane`` / ``h_far`` (neighbours within 1.3); > 1, cells that grow by this
    factor away from the edge until they reach ``h_membrane`` / ``h_far``, then stay uniform —
    a geometric grading towards the edge, where the continuum strain is singular.
    """

    length: float = 50.0
    skin_thickness: float = 0.6
    muscle_thickness: float = 10.0
    membrane_size: float = 20.0
    membrane_thickness: float = 1.0
    h_membrane: float = 0.5
    h_far: float = 2.0
    h_edge: float = 0.0
    edge_growth: float = 0.0
    skin_layers: int = 1
    muscle_layers: int = 5
    membrane_layers: int = 1

    @property
    def edge_refined(self) -> bool:
        """The membrane edge has its own, smaller cells (``0 < h_edge < h_membrane``)."""
        return 0 < self.h_edge < self.h_membrane

    def validate(self, prefix: str = "mesh") -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name not in ("h_edge", "edge_growth"):
                _check(value > 0, f"{prefix}.{f.name}", f"must be > 0, got {value}")
        _check(
            0 <= self.h_edge <= self.h_membrane,
            f"{prefix}.h_edge",
            f"must be 0 (no edge refinement) or in (0, mesh.h_membrane], got {self.h_edge}",
        )
        _check(
            self.edge_growth == 0 or 1 < self.edge_growth <= MAX_EDGE_GROWTH,
            f"{prefix}.edge_growth",
            f"must be 0 (one progression per side) or in (1, {MAX_EDGE_GROWTH:g}], got {self.edge_growth}",
        )
        _check(
            self.edge_growth == 0 or self.edge_refined,
            f"{prefix}.edge_growth",
            "grades the cells of mesh.h_edge: set mesh.h_edge in (0, mesh.h_membrane) too",
        )
        _check(
            self.membrane_size < self.length,
            f"{prefix}.membrane_size",
            f"must be smaller than mesh.length = {self.length}",
        )
        _check(
            self.h_membrane <= self.membrane_size / 2,
            f"{prefix}.h_membrane",
            "must allow at least two cells across the membrane",
        )
        _check(self.h_far >= self.h_membrane, f"{prefix}.h_far", "must be >= mesh.h_membrane")


@dataclass(frozen=True)
class SkinConfig:
    """Holzapfel–Gasser–Ogden skin: constitutive choices that are not identified.

    ``bulk_ratio`` is K/mu of the volumetric term (paper text: 20). ``fiber_invariant``
    selects the isochoric pseudo-invariant I4bar (paper, Abaqus) or the full I4 in the fiber
    term.
    """

    bulk_ratio: float = 20.0
    fiber_invariant: str = "isochoric"

    def validate(self, prefix: str = "skin") -> None:
        _check(self.bulk_ratio > 0, f"{prefix}.bulk_ratio", f"must be > 0, got {self.bulk_ratio}")
        _check(
            self.fiber_invariant in ("isochoric", "full"),
            f"{prefix}.fiber_invariant",
            f"must be 'isochoric' or 'full', got {self.fiber_invariant!r}",
        )


@dataclass(frozen=True)
class MuscleConfig:
    """Neo-Hookean muscle (not identified). mu in MPa; bulk modulus K = bulk_ratio * mu."""

    mu: float = 0.0035
    bulk_ratio: float = 20.0

    def validate(self, prefix: str = "muscle") -> None:
        _check(self.mu > 0, f"{prefix}.mu", f"must be > 0 MPa, got {self.mu}")
        _check(self.bulk_ratio > 0, f"{prefix}.bulk_ratio", f"must be > 0, got {self.bulk_ratio}")


@dataclass(frozen=True)
class MembraneConfig:
    """Active membrane: an orthotropic lamina (MPa) on top of the skin, axis 1 = x.

    ``model = "elastic"``: a bonded solid layer with plane-stress lamina stiffness and an
    imposed eigen-strain. ``model = "rigid"``: no membrane cells; the footprint's in-plane
    displacement is prescribed as u = t (alpha11 x, alpha22 y) — the infinitely stiff limit.
    ``E3`` is the through-thickness modulus of the solid layer (decoupled from the in-plane
    lamina, so the in-plane response is exactly the lamina's).
    """

    model: str = "elastic"
    E1: float = 10_000.0
    E2: float = 5_000.0
    nu12: float = 0.481
    G12: float = 5_000.0
    G13: float = 2_000.0
    G23: float = 2_000.0
    E3: float = 5_000.0

    def validate(self, prefix: str = "membrane") -> None:
        _check(
            self.model in ("elastic", "rigid"),
            f"{prefix}.model",
            f"must be 'elastic' or 'rigid', got {self.model!r}",
        )
        for name in ("E1", "E2", "G12", "G13", "G23", "E3"):
            value = getattr(self, name)
            _check(value > 0, f"{prefix}.{name}", f"must be > 0 MPa, got {value}")
        nu21 = self.nu12 * self.E2 / self.E1
        _check(
            self.nu12 * nu21 < 1 and self.nu12 > -1,
            f"{prefix}.nu12",
            f"gives an indefinite lamina stiffness (nu12 = {self.nu12})",
        )


@dataclass(frozen=True)
class SolverConfig:
    """Discretisation and Newton solver settings.

    ``quadrature_degree`` is set explicitly (UFL's estimate for the J^(-2/3) terms is ~33).
    Convergence: Newton stops when the residual norm (N) falls below ``atol`` or below
    ``rtol`` times the residual at the increment's predictor. The residual is dominated by
    the stiff membrane and has a round-off floor near 1e-11 N, so ``atol`` must stay above
    it; 1e-10 N is ~1e-5 of a skin nodal force on the paper mesh.

    Linear solves: the MUMPS LU factorisation of the tangent is reused as the (right)
    preconditioner of GMRES across Newton iterations and increments; GMRES stops at the
    relative tolerance ``krylov_rtol`` or at an absolute residual of ``atol`` / 10; the LU is
    refactorised at the next increment once an increment needed more than
    ``refactor_krylov`` GMRES iterations per Newton step (and before retrying a failed
    increment). ``refactor_krylov = 0`` factorises at every Newton step (plain Newton-LU).
    """

    element_degree: int = 1
    quadrature_degree: int = 2
    increments: int = 10
    max_cutbacks: int = 8
    max_iterations: int = 25
    rtol: float = 1e-10
    atol: float = 1e-10
    refactor_krylov: int = 10
    krylov_rtol: float = 1e-8

    def validate(self, prefix: str = "solver") -> None:
        _check(self.element_degree in (1, 2), f"{prefix}.element_degree", "must be 1 or 2")
        _check(self.quadrature_degree >= 1, f"{prefix}.quadrature_degree", "must be >= 1")
        _check(self.increments >= 1, f"{prefix}.increments", "must be >= 1")
        _check(self.max_cutbacks >= 0, f"{prefix}.max_cutbacks", "must be >= 0")
        _check(self.max_iterations >= 1, f"{prefix}.max_iterations", "must be >= 1")
        _check(0 < self.rtol < 1, f"{prefix}.rtol", "must be in (0, 1)")
        _check(self.atol >= 0, f"{prefix}.atol", "must be >= 0")
        _check(self.refactor_krylov >= 0, f"{prefix}.refactor_krylov", "must be >= 0")
        _check(0 < self.krylov_rtol < 1, f"{prefix}.krylov_rtol", "must be in (0, 1)")


OBSERVABLES = ("top_cell_average", "surface")


@dataclass(frozen=True)
class ObservableConfig:
    """What a simulation reports for each top skin cell (:mod:`skinfem.strain`).

    ``kind = "surface"``: the log strain of the skin surface z = 0 at the centre of the cell's
    top face — what a DIC camera sees, and converged under refinement through the thickness.
    ``kind = "top_cell_average"``: the average of ln V over the cell (mid-thickness with one
    skin layer; it moves with the number of skin layers; the default before datasets recorded
    their observable). Every dataset records its kind.
    """

    kind: str = "surface"

    def validate(self, prefix: str = "observable") -> None:
        _check(
            self.kind in OBSERVABLES, f"{prefix}.kind", f"must be one of {', '.join(OBSERVABLES)}, got {self.kind!r}"
        )


def _default_bounds() -> dict[str, list[float]]:
    return {
        "mu": [0.000543, 0.00206],
        "k1": [0.0117, 0.0225],
        "k2": [8.31, 15.32],
        "kappa": [0.27, 0.30],
        "theta": [0.0, 90.0],
    }


def _paper_designs() -> list[list[float]]:
    alphas22 = [-0.05 + 0.1 * i / 6 for i in range(7)]
    return [[a11, round(a22, 12)] for a11 in (-0.05, 0.05) for a22 in alphas22]


@dataclass(frozen=True)
class SweepConfig:
    """Latin hypercube over the skin parameters x membrane designs.

    ``bounds`` maps each of mu [MPa], k1 [MPa], k2 [-], kappa [-], theta [deg] to [low, high].
    ``designs`` is a list of [alpha11, alpha22] eigen-strains.
    """

    n_materials: int = 120
    seed: int = 122
    n_test: int = 20
    bounds: dict[str, list[float]] = field(default_factory=_default_bounds)
    designs: list[list[float]] = field(default_factory=_paper_designs)

    @property
    def box(self) -> np.ndarray:
        """(5, 2) [low, high] of each skin parameter, in PARAM_NAMES order (units as ``bounds``)."""
        return np.array([self.bounds[name] for name in PARAM_NAMES], dtype=float)

    def validate(self, prefix: str = "sweep") -> None:
        _check(self.n_materials >= 1, f"{prefix}.n_materials", "must be >= 1")
        _check(
            0 <= self.n_test < self.n_materials,
            f"{prefix}.n_test",
            f"must be in [0, n_materials) = [0, {self.n_materials})",
        )
        _check(
            set(self.bounds) == set(PARAM_NAMES),
            f"{prefix}.bounds",
            f"needs exactly the keys {', '.join(PARAM_NAMES)}; got {', '.join(self.bounds)}",
        )
        for name, pair in self.bounds.items():
            key = f"{prefix}.bounds.{name}"
            _check(
                isinstance(pair, (list, tuple)) and len(pair) == 2,
                key,
                "must be a pair [low, high]",
            )
            _check(
                all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in pair),
                key,
                f"must be two finite numbers [low, high], got {pair!r}",
            )
            low, high = float(pair[0]), float(pair[1])
            _check(low <= high, key, f"low {low} > high {high}")
        from skinfem.params import Design, SkinParams  # local: params imports this module

        for corner in (0, 1):
            try:
                SkinParams(**{n: float(self.bounds[n][corner]) for n in PARAM_NAMES})
            except ValueError as exc:
                raise ConfigError(f"config key '{prefix}.bounds': {exc}") from None
        _check(len(self.designs) >= 1, f"{prefix}.designs", "must list at least one design")
        for i, d in enumerate(self.designs):
            key = f"{prefix}.designs[{i}]"
            _check(isinstance(d, (list, tuple)) and len(d) == 2, key, "must be [alpha11, alpha22]")
            try:
                Design(float(d[0]), float(d[1]))
            except ValueError as exc:
                raise ConfigError(f"config key '{key}': {exc}") from None


SECTIONS: dict[str, type] = {
    "mesh": MeshConfig,
    "skin": SkinConfig,
    "muscle": MuscleConfig,
    "membrane": MembraneConfig,
    "solver": SolverConfig,
    "observable": ObservableConfig,
    "sweep": SweepConfig,
}


@dataclass(frozen=True)
class Config:
    """The full configuration: one frozen dataclass per TOML section."""

    name: str = "custom"
    mesh: MeshConfig = field(default_factory=MeshConfig)
    skin: SkinConfig = field(default_factory=SkinConfig)
    muscle: MuscleConfig = field(default_factory=MuscleConfig)
    membrane: MembraneConfig = field(default_factory=MembraneConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    observable: ObservableConfig = field(default_factory=ObservableConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)

    def validate(self) -> Config:
        for section in SECTIONS:
            getattr(self, section).validate(section)
        return self

    def to_toml(self) -> str:
        """The configuration as TOML text (every key, defaults included)."""
        lines = [f'name = "{self.name}"', ""]
        for section in SECTIONS:
            lines.append(f"[{section}]")
            for key, value in dataclasses.asdict(getattr(self, section)).items():
                lines.append(f"{key} = {_toml_value(value)}")
            lines.append("")
        return "\n".join(lines)

    def with_changes(self, **sections: dict[str, Any]) -> Config:
        """A copy with some keys of some sections replaced, validated.

        Example: ``cfg.with_changes(mesh={"h_far": 4.0})``.
        """
        new = {}
        for section, changes in sections.items():
            _check(section in SECTIONS, section, f"unknown section; known: {', '.join(SECTIONS)}")
            new[section] = _build_section(section, {**dataclasses.asdict(getattr(self, section)), **changes})
        return dataclasses.replace(self, **new).validate()

    @property
    def mesh_key(self) -> str:
        """A short hash naming the mesh this configuration needs (geometry + membrane model)."""
        text = repr(dataclasses.asdict(self.mesh)) + self.membrane.model
        return hashlib.sha256(text.encode()).hexdigest()[:10]


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else "nan"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return str(value)


def _build_section(section: str, values: dict[str, Any]):
    cls = SECTIONS[section]
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ConfigError(f"config key '{section}.{unknown[0]}': unknown key; known keys: {', '.join(known)}")
    kwargs = {}
    defaults = cls()
    for key, value in values.items():
        expected = type(getattr(defaults, key))
        dotted = f"{section}.{key}"
        if expected is float:
            _check(
                isinstance(value, (int, float)) and not isinstance(value, bool),
                dotted,
                f"expected a number, got {value!r}",
            )
            _check(math.isfinite(value), dotted, f"must be a finite number, got {value!r}")
            value = float(value)
        elif expected is int:
            _check(
                isinstance(value, int) and not isinstance(value, bool),
                dotted,
                f"expected an integer, got {value!r}",
            )
        else:
            _check(
                isinstance(value, expected),
                dotted,
                f"expected {expected.__name__}, got {value!r}",
            )
        kwargs[key] = value
    return cls(**kwargs)


def config_from_dict(data: dict[str, Any], name: str = "custom") -> Config:
    """Build and validate a :class:`Config` from parsed TOML."""
    data = dict(data)
    name = str(data.pop("name", name))
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"config key '{unknown[0]}': unknown section; known: name, {', '.join(SECTIONS)}")
    sections = {}
    for section, values in data.items():
        _check(isinstance(values, dict), section, "must be a table, e.g. [mesh]")
        sections[section] = _build_section(section, values)
    return Config(name=name, **sections).validate()


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_config(source: str | Path) -> Config:
    """Load a configuration from a TOML path or a built-in preset name.

    Raises:
        ConfigError: the file is missing, not valid TOML, or holds a bad key.
    """
    path = Path(source)
    if not path.suffix and not path.exists():
        if str(source) not in preset_names():
            raise ConfigError(
                f"config '{source}': no such file and no such preset (presets: {', '.join(preset_names())})"
            )
        path = PRESET_DIR / f"{source}.toml"
    if path.is_dir():
        raise ConfigError(f"config '{path}' is a folder, not a TOML file")
    if not path.is_file():
        raise ConfigError(f"config file '{path}' does not exist")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"config file '{path}' is not UTF-8 text (TOML)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file '{path}': invalid TOML: {exc}") from None
    return config_from_dict(data, name=path.stem)


def config_from_toml(text: str) -> Config:
    """Rebuild a configuration from the TOML text stored in an output file."""
    return config_from_dict(tomllib.loads(text))
