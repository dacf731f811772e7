import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbgcomp import optics

wavelengths = st.floats(1500.0, 1600.0)
elongations = st.floats(-500.0, 500.0)  # µm over a 0.1-2 m path: |strain| <= 5e-3
gauges = st.floats(100.0, 2000.0)
temps = st.floats(-40.0, 60.0)


@settings(max_examples=300, deadline=None)
@given(wavelengths, elongations, gauges, temps)
def test_wavelength_elongation_round_trip(l0, dl, gauge, dt):
    lam = optics.wavelength_nm(dl, l0, gauge, dt)
    back = optics.elongation_um(lam, l0, gauge, dt)
    assert back == pytest.approx(dl, abs=1e-9 * max(1.0, abs(dl)) + 1e-7)


@settings(max_examples=200, deadline=None)
@given(wavelengths, st.floats(-5.0, 5.0), gauges)
def test_elongation_wavelength_round_trip(l0, shift_nm, gauge):
    lam = l0 + shift_nm
    dl = optics.elongation_um(lam, l0, gauge, 3.0)
    assert optics.wavelength_nm(dl, l0, gauge, 3.0) == pytest.approx(lam, abs=1e-9)


def test_strain_sensitivity_matches_the_textbook_1_2_pm_per_microstrain():
    # A 1550 nm grating shifts ~1.2 pm per µε: (1 - 0.22) * 1550 nm * 1e-6.
    assert optics.strain_sensitivity_nm(1550.0) * 1e-6 == pytest.approx(1.209e-3, rel=1e-3)
    # and ~11.2 pm/K for temperature (eq. 3): (0.55e-6 + 6.67e-6) * 1550 nm.
    assert optics.temperature_sensitivity_nm_per_K(1550.0) == pytest.approx(0.011191, rel=1e-4)


def test_hand_computed_elongation():
    # 500 mm path, +0.6045 nm at 1550 nm, no temperature change:
    # strain = 0.6045/1550/0.78 = 5.0e-4 -> 250 µm.
    assert optics.elongation_um(1550.6045, 1550.0, 500.0) == pytest.approx(250.0, rel=1e-12)
    assert optics.uncompensated_strain(1550.6045, 1550.0) == pytest.approx(5.0e-4, rel=1e-12)


def test_free_fibre_heating_reads_as_its_own_expansion():
    # An unbonded grating heated by dT shifts by (alpha_f + xi) * lambda0 * dT (eq. 3); the
    # compensated host strain is then the fibre's own free expansion alpha_f * dT.
    l0, dt = 1540.0, 7.0
    lam = l0 + optics.temperature_sensitivity_nm_per_K(l0) * dt
    eps = optics.host_strain(lam, l0, dt)
    assert eps == pytest.approx(optics.FIBRE_CTE_PER_K * dt, rel=1e-9)


def test_bonded_on_host_that_only_expands_thermally():
    # Host with CTE 12e-6/K heated by 5 K: the compensated reading is exactly the host's thermal
    # strain, whatever the fibre constants.
    l0, dt, cte = 1535.0, 5.0, 12e-6
    lam = optics.wavelength_nm(
        cte * dt * 400.0 * 1e3,
        l0,
        400.0,
        dt,
        photoelastic=0.2,
        thermo_optic_per_K=7e-6,
        fibre_cte_per_K=0.5e-6,
    )
    eps = optics.host_strain(lam, l0, dt, photoelastic=0.2, thermo_optic_per_K=7e-6, fibre_cte_per_K=0.5e-6)
    assert eps == pytest.approx(cte * dt, rel=1e-9)
    # Ignoring temperature over-reads it by the thermo-optic effect.
    assert optics.uncompensated_strain(lam, l0, photoelastic=0.2) > 1.5 * cte * dt


def test_vectorised_over_samples_and_sensors():
    lam0 = np.array([1530.0, 1540.0, 1550.0])
    lam = lam0 + np.array([[0.0, 0.1, -0.2], [0.3, 0.0, 0.1]])
    gauge = np.array([500.0, 500.0, 400.0])
    dt = np.array([[0.0, 1.0, 2.0], [1.0, 1.0, 1.0]])
    out = optics.elongation_um(lam, lam0, gauge, dt)
    assert out.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            assert out[i, j] == pytest.approx(optics.elongation_um(lam[i, j], lam0[j], gauge[j], dt[i, j]))


def test_bragg_wavelength_eq1():
    assert optics.bragg_wavelength_nm(1.447, 535.6) == pytest.approx(2 * 1.447 * 535.6)
