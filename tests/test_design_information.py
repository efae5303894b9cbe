"""benchmarks/design_information.py: Cramér–Rao widths and regional shares of a Jacobian (no FE)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.scripts import ROOT, load_script


@pytest.fixture(scope="module")
def design_information():
    return load_script(ROOT / "benchmarks" / "design_information.py", "design_information")


def test_widths_are_the_least_squares_covariance_in_prior_units(design_information):
    """For y = J x + noise the least-squares estimate of x has covariance σ² (JᵀJ)⁻¹: the widths
    equal 3.92 sd of that estimate over the prior range, here checked by simulation."""
    rng = np.random.default_rng(0)
    n, sigma = 400, 1e-3
    jacobian = rng.normal(size=(n, 3, 5)) * np.array([1e2, 1.0, 1e-3, 10.0, 1e-2])
    prior_range = np.array([1.5e-3, 0.011, 7.0, 0.03, 90.0])
    info = design_information.information(jacobian, np.linspace(0, 20, n), prior_range, sigma)
    flat = jacobian.reshape(-1, 5)
    estimates = np.linalg.lstsq(flat, sigma * rng.normal(size=(flat.shape[0], 4000)), rcond=None)[0]
    simulated = 3.92 * estimates.std(axis=1) / prior_range
    np.testing.assert_allclose([info.width_95[p] for p in design_information.PARAMS], simulated, rtol=0.05)


def test_region_shares_partition_the_information_and_locate_a_local_column(design_information):
    rng = np.random.default_rng(1)
    ring = rng.uniform(0, 20, size=300)
    jacobian = rng.normal(size=(300, 3, 5))
    jacobian[ring >= 8, :, 4] = 0.0  # theta seen under the membrane only
    info = design_information.information(jacobian, ring, np.ones(5), 1e-3)
    totals = np.sum([list(share.values()) for share in info.region_share.values()], axis=0)
    np.testing.assert_allclose(totals, 1.0, rtol=1e-12)
    assert info.region_share["under the membrane"]["theta"] == pytest.approx(1.0)
    assert info.region_share["far field"]["theta"] == 0.0


def test_a_design_is_a_name_and_two_eigen_strains(design_information):
    assert design_information.parse_design("mixed=0.05,-0.05") == ("mixed", (0.05, -0.05))


def test_medians_over_materials_per_design_and_observable(design_information):
    def entry(width):
        share = {"edge band 8-12 mm": dict.fromkeys(design_information.PARAMS, width / 10)}
        widths = dict.fromkeys(design_information.PARAMS, width)
        return {"width_95": widths, "width_95_xx_yy": widths, "region_share": share}

    record = {
        m: {"mixed": {o: entry(w) for o in design_information.OBSERVABLES}} for m, w in (("centre", 0.1), ("3", 0.3))
    }
    summary = design_information.medians(record)
    assert summary["mixed"]["surface"]["width_95"]["theta"] == pytest.approx(0.2)
    assert summary["mixed"]["top_cell_average"]["region_share"]["edge band 8-12 mm"]["mu"] == pytest.approx(0.02)
    assert "| mixed | surface | E_xx, E_yy, E_xy | 0.2 (2%) |" in design_information.table(summary)
