"""FE twin of the ram verified against closed forms (beam theory, free thermal expansion,
thermal bending) and against a full-order implicit-Euler integration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

import fbgcomp_testing
from fbgcomp.errors import InputError
from fbgcomp.structure import load_machine

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "src" / "fbgcomp" / "data" / "ram.yaml"


@pytest.fixture(scope="module")
def machine():
    return load_machine()


@pytest.fixture(scope="module")
def fe():
    """The FE parts: scikit-fem is the optional ``fe`` extra."""
    fbgcomp_testing.require("skfem")
    from types import SimpleNamespace

    from fbgcomp.structure import Twin, elastic
    from fbgcomp.structure.fe import Factorised, layer_order
    from fbgcomp.structure.mesh import build_mesh
    return SimpleNamespace(Twin=Twin, elastic=elastic, Factorised=Factorised,
                           layer_order=layer_order, build_mesh=build_mesh)


@pytest.fixture(scope="module")
def twin(machine, fe):
    return fe.Twin(machine, resolution=0.5)


def _box(fe, machine, length_mm, resolution):
    return fe.build_mesh(half_width_mm=machine.ram.outer_width_mm / 2,
                      half_depth_mm=machine.ram.outer_depth_mm / 2, wall_mm=machine.ram.wall_mm,
                      length_mm=length_mm, n_wall=max(1, round(3 * resolution)),
                      n_span=round(10 * resolution), dz_mm=20 / resolution)


# ------------------------------------------------------------------------------------- machine
def test_default_machine_is_the_papers_ram(machine):
    assert [s.name for s in machine.sensors] == ["S1", "S2", "S3", "S4", "S5"]
    assert [s.face for s in machine.sensors] == ["+X", "-X", "+Y", "-Y", "+X"]
    assert machine.sensors[4].gauge_length == pytest.approx(400.0)
    assert machine.ttp_z_mm == pytest.approx(-250.0)
    assert [p.name for p in machine.probes] == ["T_bulk", "T_surf", "T_flange", "T_amb"]
    assert (Path(__file__).resolve().parents[1] / "examples" / "ram.yaml").resolve() == DEFAULT_YAML


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["sensors"][2].__setitem__("lambda0_nm", -1530), "field sensors[2].lambda0_nm"),
    (lambda d: d["sensors"][1].__setitem__("temperature_probe", "T_nowhere"),
     "field sensors[1].temperature_probe"),
    (lambda d: d["materials"]["cfrp"].pop("E_L_GPa"), "field materials.cfrp.E_L_GPa"),
    (lambda d: d["ram"].__setitem__("wal_mm", 20), "field ram.wal_mm"),
    (lambda d: d["probes"][0].__setitem__("y_mm", 0.0), "field probes[0]"),
    (lambda d: d["sensors"][4].__setitem__("z_end_mm", 1500.0), "field sensors[4].z_end_mm"),
    (lambda d: d["supports"]["carriages"][1].__setitem__("z_mm", 1300.0),
     "field supports.carriages[1].z_mm"),
])
def test_yaml_errors_name_the_file_and_field(tmp_path, edit, field):
    data = yaml.safe_load(DEFAULT_YAML.read_text())
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError) as err:
        load_machine(path)
    assert err.value.column == field
    assert err.value.file == str(path)
    assert "\n" not in str(err.value)


def test_unreadable_yaml_is_an_input_error(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("ram: [1, 2\n")
    with pytest.raises(InputError, match="invalid YAML"):
        load_machine(path)


# ------------------------------------------------------------------------------ closed forms
def test_cantilever_box_tip_force_matches_timoshenko(machine, fe):
    """Slender box (L/h ~ 10) clamped at z = 0, tip force F_x at z = L: bending + shear."""
    L, F = 2400.0, 1000.0
    rm = _box(fe, machine, L, 0.7)
    vb, _, K, _ = fe.elastic.assemble_elasticity(rm, machine.materials.cfrp, machine.materials.steel)
    tip = fe.elastic.rigid_extension_rows(vb, rm.end_facets(L))
    from skfem import condense
    clamped = vb.get_dofs(lambda x: np.abs(x[2]) < 1e-6).all()
    Kc, fc, _, free = condense(K, tip[0] * F, D=clamped)
    u = np.zeros(vb.N)
    rank = np.argsort(fe.layer_order(rm.mesh.p, vb.nodal_dofs))     # position of each DOF in layers
    u[free] = fe.Factorised(Kc, order=np.argsort(rank[free])).solve(fc)
    fe_um = 1e3 * tip[0] @ u

    a, b, t = 125.0, 105.0, 20.0
    I = ((2 * a) ** 4 - (2 * b) ** 4) / 12
    E_L, G = 1e3 * machine.materials.cfrp.E_L_GPa, 1e3 * machine.materials.cfrp.G_LT_GPa
    bending = F * L**3 / (3 * E_L * I)
    # Shear compliance from the thin-walled shear flow q(s) on the wall centreline (c = 115 mm).
    c = (a + b) / 2
    s = np.linspace(0, c, 4001)
    q_flange = t * c * s / I                       # per unit shear force
    x = np.linspace(-c, c, 8001)
    q_web = q_flange[-1] + t * (c**2 - x**2) / (2 * I)
    shear = F * L * (4 * np.trapezoid(q_flange**2, s) + 2 * np.trapezoid(q_web**2, x)) / (G * t)
    theory_um = 1e3 * (bending + shear)
    assert fe_um == pytest.approx(theory_um, rel=0.03)


def test_uniform_heating_grows_the_ttp_by_sum_of_cte_times_length(twin, machine):
    """Determinate supports: free expansion; the TTP moves by -(CTE_L z_nut + CTE_steel H) dT."""
    dT = 10.0
    r = twin.static_temperature_response("uniform", dT)
    cf, st = machine.materials.cfrp, machine.materials.steel
    expected_dz_um = -1e3 * dT * (cf.cte_L_per_K * machine.supports.nut.z_mm
                                  + st.cte_per_K * machine.housing.height_mm)
    assert r.ttp_um[2] == pytest.approx(expected_dz_um, rel=0.01)
    assert np.abs(r.ttp_um[:2]).max() < 1e-3 * abs(expected_dz_um)
    assert r.sensor_temperature_C == pytest.approx(np.full(5, dT))


def test_uniform_heating_loads_no_support(twin):
    """Six independent supports: a compatible (free) thermal strain leaves every support unloaded."""
    theta = twin.temperature_field("uniform", 10.0)
    u = twin._elastic.solve(twin._Th @ theta)
    reactions_N = twin.support_stiffness_N_per_mm * (twin.support_rows_mm @ u)
    assert np.abs(reactions_N).max() < 1e-6 * np.abs(twin._Th @ theta).max()


def test_linear_temperature_across_box_bends_it_with_curvature_cte_dT_over_h(machine, fe):
    """T linear in X (+X face minus -X face = dT) on a free box: tip deflection kappa L^2 / 2."""
    L, dT = 1200.0, 10.0
    rm = _box(fe, machine, L, 0.6)
    cf = machine.materials.cfrp
    vb, _, K, Th = fe.elastic.assemble_elasticity(rm, cf, machine.materials.steel)
    root = rm.end_facets(0.0)
    # Statically determinate root: mean translations, best-fit rotations and twist held.
    at0 = fe.elastic.rigid_extension_rows(vb, root)
    at100 = fe.elastic.rigid_extension_rows(vb, root, lever_mm=100.0)
    first = rm.zs_mm[1]
    twist = (fe.elastic.facet_mean_rows(vb, rm.face_facets("+X", 0.0, first))[1]
             - fe.elastic.facet_mean_rows(vb, rm.face_facets("-X", 0.0, first))[1])
    rows = np.vstack([at0, at100[:2] - at0[:2], twist])
    K = K + fe.elastic.spring_matrix(rows, 1e9)
    theta = dT * rm.mesh.p[0] / (2 * rm.half_width_mm)
    u = fe.Factorised(K, order=fe.layer_order(rm.mesh.p, vb.nodal_dofs)).solve(Th @ theta)
    tip_um = 1e3 * fe.elastic.rigid_extension_rows(vb, rm.end_facets(L))[0] @ u
    kappa = -cf.cte_L_per_K * dT / (2 * rm.half_width_mm)   # hotter +X side grows: bends to -X
    assert tip_um == pytest.approx(1e3 * kappa * L**2 / 2, rel=0.05)


# --------------------------------------------------------------------------------- operators
def test_supports_remove_every_rigid_body_mode(twin):
    p = twin.mesh.mesh.p
    vb = twin._vbasis
    modes = []
    for axis in range(3):
        m = np.zeros(vb.N)
        m[vb.nodal_dofs[axis]] = 1.0
        modes.append(m)
    for axis in range(3):               # small rotations: u = e_axis x r
        m = np.zeros(vb.N)
        i, j = (axis + 1) % 3, (axis + 2) % 3
        m[vb.nodal_dofs[j]] = p[i]
        m[vb.nodal_dofs[i]] = -p[j]
        modes.append(m)
    A = twin.support_rows_mm @ np.array(modes).T
    assert A.shape == (6, 6)
    assert np.linalg.matrix_rank(A, tol=1e-8 * np.abs(A).max()) == 6


def test_static_tip_compliance_is_symmetric_positive_and_linear(twin):
    C = twin.influence.ttp_per_force_um_per_N
    assert np.allclose(C, C.T, atol=1e-9 * np.abs(C).max())          # Maxwell-Betti
    assert np.all(np.linalg.eigvalsh(0.5 * (C + C.T)) > 0)
    F = np.array([[1000.0, 0, 0], [0, 2000.0, 0], [1000.0, 2000.0, -500.0]])
    r = twin.static(F)
    assert r.ttp_um.shape == (3, 3) and r.sensor_elongation_um.shape == (3, 5)
    assert np.allclose(r.ttp_um[2], r.ttp_um[0] + r.ttp_um[1] + twin.static([0, 0, -500.0]).ttp_um[0])
    # Bending about Y stretches the -X side and shortens +X: S1 and S2 read opposite signs.
    assert r.sensor_elongation_um[0, 0] == pytest.approx(-r.sensor_elongation_um[0, 1], rel=1e-6)


def test_reduced_thermal_integrator_matches_implicit_euler(twin):
    """Short window with an ambient swing, a spindle step and a radiant step."""
    t = np.arange(0.0, 1201.0, 1.0)
    ambient = 30.0 + 2.0 * np.sin(2 * np.pi * t / 1800)
    spindle = np.where(t >= 60, 300.0, 0.0)
    radiant = np.where(t >= 400, 100.0, 0.0)
    red = twin.thermal(t, ambient, spindle, radiant, initial_C=30.0)
    ref = twin.thermal_direct(t, ambient, spindle, radiant, initial_C=30.0)
    for name in ("sensor_elongation_um", "sensor_temperature_C", "probe_C", "ttp_um"):
        a, b = getattr(red, name), getattr(ref, name)
        span = np.ptp(b, axis=0)
        live = span > 1e-6 * np.abs(b).max()        # outputs that move at all in this window
        assert live.any()
        err = np.abs(a - b).max(axis=0)[live] / span[live]
        assert err.max() < 0.01, (name, err)
    assert red.probe("T_amb") == pytest.approx(ambient)


def test_thermal_steady_state_equals_static_temperature_superposition(twin):
    """A long constant ambient offset settles to the uniform-heating response (linearity)."""
    t = np.arange(0.0, 30 * 86400.0, 600.0)
    h = twin.thermal(t, np.full(t.shape, 25.0), 0.0, initial_C=25.0)
    Tref = twin.machine.reference_temperature_C
    uniform = twin.static_temperature_response("uniform", 25.0 - Tref)
    assert h.ttp_um[-1] == pytest.approx(uniform.ttp_um, abs=1e-6 * np.abs(uniform.ttp_um).max())
    assert h.sensor_temperature_C[-1] == pytest.approx(np.full(5, 25.0))


def test_z_axis_position_moves_the_carriages_and_the_lever_arm(machine, fe):
    """Raising the ram (Z+) brings the carriages closer to the TTP: the tip gets stiffer."""
    low = fe.Twin(machine, resolution=0.4, z_axis_mm=0.0)
    raised = fe.Twin(machine, resolution=0.4, z_axis_mm=300.0)
    assert raised.z_axis_mm == 300.0
    c_low = low.influence.ttp_per_force_um_per_N
    c_raised = raised.influence.ttp_per_force_um_per_N
    assert c_raised[0, 0] < 0.8 * c_low[0, 0]
    assert c_raised[2, 2] == pytest.approx(c_low[2, 2], rel=0.02)   # the nut travels with the ram
    with pytest.raises(InputError, match="off the ram"):
        fe.Twin(machine, resolution=0.4, z_axis_mm=1000.0)


def test_extra_paths_reproduce_the_built_in_sensors(twin, machine):
    """Placement candidates go through the same operators: S1..S5 given as paths match."""
    paths = twin.path_influence(machine.sensors)
    assert paths.names == twin.sensor_names
    assert np.allclose(paths.per_force_um_per_N, twin.influence.sensor_per_force_um_per_N)
    t = np.arange(0.0, 3601.0, 10.0)
    ambient = 30.0 + np.sin(t / 900)
    spindle = np.where(t > 600, 200.0, 0.0)
    elong, temp = twin.thermal_paths(paths, t, ambient, spindle, initial_C=30.0)
    h = twin.thermal(t, ambient, spindle, initial_C=30.0)
    assert np.allclose(elong, h.sensor_elongation_um, atol=1e-9)
    assert np.allclose(temp, h.sensor_temperature_C, atol=1e-9)
