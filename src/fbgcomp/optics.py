"""Fibre Bragg grating optics: wavelength <-> strain <-> elongation (paper eq. 1-4).

A bonded long-gauge FBG follows the total strain of its host along the gauge, ``eps_host`` (the
mechanical strain plus the host's own thermal expansion). The fibre's own free expansion
``alpha_f * dT`` is part of that imposed strain, so the mechanical strain of the fibre is
``eps_host - alpha_f * dT``. With ``p_e`` the effective photo-elastic coefficient, ``xi`` the
thermo-optic coefficient and ``dT`` the grating's temperature change (paper eq. 2):

    d_lambda / lambda_0 = (1 - p_e) * (eps_host - alpha_f * dT) + (alpha_f + xi) * dT

Inverting it gives the temperature-compensated host strain, and the elongation of the sensor
path is that strain times the gauge length (eq. 4). Without a temperature (``dT = 0``) the same
formula is the uncompensated form that attributes the whole wavelength shift to strain.

All functions are pure and vectorised: scalars, numpy arrays or pandas Series broadcast, so one
sample and a 36 h campaign go through the same code.

References
----------
.. [1] A Kinematic Model to Compensate the Structural Deformations in Machine Tools Using Fibre
   Bragg Grating (FBG) Sensors, eq. (1)-(4). ``shared/reference/fbg-kinematic-compensation-paper.md``.
"""

from __future__ import annotations

import numpy as np

#: Effective photo-elastic coefficient of silica fibre (dimensionless).
PHOTOELASTIC = 0.22
#: Thermo-optic coefficient xi of silica fibre, 1/K.
THERMO_OPTIC_PER_K = 6.67e-6
#: Coefficient of thermal expansion of silica fibre alpha_f, 1/K.
FIBRE_CTE_PER_K = 0.55e-6

_UM_PER_MM = 1e3


def bragg_wavelength_nm(effective_index, grating_period_nm):
    """Bragg wavelength of a grating (paper eq. 1): ``lambda = 2 * n_eff * Lambda``.

    Parameters
    ----------
    effective_index : array_like
        Effective refractive index of the fibre core mode (dimensionless, ~1.447).
    grating_period_nm : array_like
        Grating period Lambda in nm (~530 nm for a 1550 nm grating).

    Returns
    -------
    ndarray
        Bragg wavelength in nm.
    """
    return 2.0 * np.asarray(effective_index, dtype=float) * np.asarray(grating_period_nm, dtype=float)


def relative_shift(wavelength_nm, wavelength0_nm):
    """Relative Bragg shift ``d_lambda / lambda_0`` (dimensionless), with ``lambda_0`` the zero state."""
    wavelength0_nm = np.asarray(wavelength0_nm, dtype=float)
    return (np.asarray(wavelength_nm, dtype=float) - wavelength0_nm) / wavelength0_nm


def host_strain(
    wavelength_nm,
    wavelength0_nm,
    delta_t_C=0.0,
    *,
    photoelastic=PHOTOELASTIC,
    thermo_optic_per_K=THERMO_OPTIC_PER_K,
    fibre_cte_per_K=FIBRE_CTE_PER_K,
):
    """Temperature-compensated total strain of the host under a bonded FBG (paper eq. 2-3).

    ``eps_host = [d_lambda/lambda_0 - (alpha_f + xi) * dT] / (1 - p_e) + alpha_f * dT``

    Parameters
    ----------
    wavelength_nm : array_like
        Measured Bragg wavelength, nm.
    wavelength0_nm : array_like
        Bragg wavelength in the zero state, nm.
    delta_t_C : array_like, default 0
        Temperature change of the grating since the zero state, K (°C difference). Zero gives
        the uncompensated strain (the whole shift read as strain).
    photoelastic : float
        Effective photo-elastic coefficient p_e (dimensionless).
    thermo_optic_per_K : float
        Thermo-optic coefficient xi, 1/K.
    fibre_cte_per_K : float
        Thermal expansion coefficient of the fibre alpha_f, 1/K.

    Returns
    -------
    ndarray
        Host strain along the gauge (m/m, dimensionless).
    """
    delta_t_C = np.asarray(delta_t_C, dtype=float)
    shift = relative_shift(wavelength_nm, wavelength0_nm)
    return (shift - (fibre_cte_per_K + thermo_optic_per_K) * delta_t_C) / (
        1.0 - photoelastic
    ) + fibre_cte_per_K * delta_t_C


def uncompensated_strain(wavelength_nm, wavelength0_nm, *, photoelastic=PHOTOELASTIC):
    """Strain read from the Bragg shift alone, ignoring temperature (eq. 2 with dT = 0)."""
    return relative_shift(wavelength_nm, wavelength0_nm) / (1.0 - photoelastic)


def elongation_um(
    wavelength_nm,
    wavelength0_nm,
    gauge_length_mm,
    delta_t_C=0.0,
    *,
    photoelastic=PHOTOELASTIC,
    thermo_optic_per_K=THERMO_OPTIC_PER_K,
    fibre_cte_per_K=FIBRE_CTE_PER_K,
):
    """Elongation dL of a long-gauge sensor path, temperature-compensated (paper eq. 2-4).

    ``dL = eps_host * L_gauge`` (eq. 4), reported in µm.

    Parameters
    ----------
    wavelength_nm, wavelength0_nm : array_like
        Measured and zero-state Bragg wavelengths, nm.
    gauge_length_mm : array_like
        Length of the bonded sensor path, mm.
    delta_t_C : array_like, default 0
        Temperature change of the grating since the zero state, K. Zero: uncompensated.
    photoelastic, thermo_optic_per_K, fibre_cte_per_K : float
        Fibre constants, see :func:`host_strain`.

    Returns
    -------
    ndarray
        Elongation of the host along the path, µm.
    """
    strain = host_strain(
        wavelength_nm,
        wavelength0_nm,
        delta_t_C,
        photoelastic=photoelastic,
        thermo_optic_per_K=thermo_optic_per_K,
        fibre_cte_per_K=fibre_cte_per_K,
    )
    return strain * np.asarray(gauge_length_mm, dtype=float) * _UM_PER_MM


def wavelength_nm(
    elongation_um,
    wavelength0_nm,
    gauge_length_mm,
    delta_t_C=0.0,
    *,
    photoelastic=PHOTOELASTIC,
    thermo_optic_per_K=THERMO_OPTIC_PER_K,
    fibre_cte_per_K=FIBRE_CTE_PER_K,
):
    """Bragg wavelength of a bonded FBG whose host path elongates by ``elongation_um`` (eq. 2, 4).

    The forward model used by the virtual test bench and the simulated interrogator; exact
    inverse of :func:`elongation_um`.

    Parameters
    ----------
    elongation_um : array_like
        Total elongation of the host along the path (mechanical + thermal), µm.
    wavelength0_nm : array_like
        Zero-state Bragg wavelength, nm.
    gauge_length_mm : array_like
        Sensor path length, mm.
    delta_t_C : array_like, default 0
        Temperature change of the grating itself since the zero state, K.

    Returns
    -------
    ndarray
        Bragg wavelength, nm.
    """
    delta_t_C = np.asarray(delta_t_C, dtype=float)
    strain = np.asarray(elongation_um, dtype=float) / (np.asarray(gauge_length_mm, dtype=float) * _UM_PER_MM)
    shift = (1.0 - photoelastic) * (strain - fibre_cte_per_K * delta_t_C) + (
        fibre_cte_per_K + thermo_optic_per_K
    ) * delta_t_C
    return np.asarray(wavelength0_nm, dtype=float) * (1.0 + shift)


def grating_temperature_change_K(
    wavelength_nm, wavelength0_nm, *, thermo_optic_per_K=THERMO_OPTIC_PER_K, fibre_cte_per_K=FIBRE_CTE_PER_K
):
    """Temperature change of a strain-free (loose, unbonded) reference grating, K (paper eq. 3
    inverted): ``dT = (d_lambda / lambda_0) / (alpha_f + xi)``.

    Placed beside a bonded sensor it reads the temperature of the sensor's own gauge, which a
    probe on another face does not; its ``dT`` then goes into :func:`host_strain`.

    Parameters
    ----------
    wavelength_nm, wavelength0_nm : array_like
        Measured and zero-state Bragg wavelengths of the reference grating, nm.
    thermo_optic_per_K, fibre_cte_per_K : float
        Fibre constants, 1/K (see :func:`host_strain`).
    """
    return relative_shift(wavelength_nm, wavelength0_nm) / (fibre_cte_per_K + thermo_optic_per_K)


def free_grating_wavelength_nm(
    delta_t_C, wavelength0_nm, *, thermo_optic_per_K=THERMO_OPTIC_PER_K, fibre_cte_per_K=FIBRE_CTE_PER_K
):
    """Bragg wavelength of a strain-free grating warmed by ``delta_t_C`` K (eq. 3), nm: the
    forward model of :func:`grating_temperature_change_K`."""
    return np.asarray(wavelength0_nm, dtype=float) * (
        1.0 + (fibre_cte_per_K + thermo_optic_per_K) * np.asarray(delta_t_C, dtype=float)
    )


def temperature_sensitivity_nm_per_K(
    wavelength0_nm, *, thermo_optic_per_K=THERMO_OPTIC_PER_K, fibre_cte_per_K=FIBRE_CTE_PER_K
):
    """Wavelength shift of a free (unbonded) grating per kelvin (paper eq. 3), nm/K."""
    return (fibre_cte_per_K + thermo_optic_per_K) * np.asarray(wavelength0_nm, dtype=float)


def strain_sensitivity_nm(wavelength0_nm, *, photoelastic=PHOTOELASTIC):
    """Wavelength shift per unit strain (eq. 2 at constant temperature), nm per (m/m)."""
    return (1.0 - photoelastic) * np.asarray(wavelength0_nm, dtype=float)


def elongation_noise_um(sensors, wavelength_noise_nm=0.001):
    """Standard deviation of each sensor's elongation (S,) µm from the interrogator's wavelength
    noise (SD, nm): the noise over the strain sensitivity (eq. 2) times the gauge length (eq. 4).

    ``sensors``: objects with ``lambda0_nm``, ``photoelastic`` and the gauge length in mm as
    ``gauge_length_mm`` (a campaign's sensor record) or ``gauge_length`` (a machine description's).
    """
    lam0 = np.array([s.lambda0_nm for s in sensors], dtype=float)
    gauge = np.array(
        [s.gauge_length if hasattr(s, "gauge_length") else s.gauge_length_mm for s in sensors], dtype=float
    )
    pe = np.array([s.photoelastic for s in sensors], dtype=float)
    return wavelength_noise_nm / strain_sensitivity_nm(lam0, photoelastic=pe) * gauge * _UM_PER_MM
