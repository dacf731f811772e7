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
from fbgcomp.structure.machine import parse_machine

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "src" / "fbgcomp" / "data" / "ram.yaml"


@pytest.fixture(scope="session")
def machine():
    return load_machine()


@pytest.fixture(scope="session")
def fe():
    """The FE parts: scikit-fem is the optional ``fe`` extra."""
    fbgcomp_testing.require("skfem")
    from types import SimpleNamespace

    from fbgcomp.structure import Twin, elastic
    from fbgcomp.structure.fe import Factorised, layer_order
    from fbgcomp.structure.mesh import build_mesh

    return SimpleNamespace(
        Twin=Twin, elastic=elastic, Factorised=Factorised, layer_order=layer_order, build_mesh=build_mesh
    )


@pytest.fixture(scope="session")
def twin(machine, fe):
    return fe.Twin(machine, resolution=0.5)


def _box(fe, machine, length_mm, resolution):
    return fe.build_mesh(
        half_width_mm=machine.ram.outer_width_mm / 2,
        half_depth_mm=machine.ram.outer_depth_mm / 2,
        wall_mm=machine.ram.wall_mm,
        length_mm=length_mm,
        n_wall=max(1, round(3 * resolution)),
        n_span=round(10 * resolution),
        dz_mm=20 / resolution,
    )


# ------------------------------------------------------------------------------------- machine
def test_default_machine_is_the_papers_ram(machine):
    assert [s.name for s in machine.sensors] == ["S1", "S2", "S3", "S4", "S5"]
    assert [s.face for s in machine.sensors] == ["+X", "-X", "+Y", "-Y", "+X"]
    assert machine.sensors[4].gauge_length == pytest.approx(400.0)
    assert machine.ttp_z_mm == pytest.approx(-250.0)
    assert [p.name for p in machine.probes] == ["T_bulk", "T_surf", "T_flange", "T_amb"]
    assert (Path(__file__).resolve().parents[1] / "examples" / "ram.yaml").resolve() == DEFAULT_YAML


def _assert_names_file_and_field(tmp_path, source_yaml, edit, field):
    """Load ``source_yaml`` edited by ``edit``: one-line InputError naming the file and field."""
    data = yaml.safe_load(source_yaml.read_text())
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError) as err:
        load_machine(path)
    assert err.value.column == field
    assert err.value.file == str(path)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["sensors"][2].__setitem__("lambda0_nm", -1530), "field sensors[2].lambda0_nm"),
        (
            lambda d: d["sensors"][1].__setitem__("temperature_probe", "T_nowhere"),
            "field sensors[1].temperature_probe",
        ),
        (lambda d: d["materials"]["cfrp"].pop("E_L_GPa"), "field materials.cfrp.E_L_GPa"),
        (lambda d: d["ram"].__setitem__("wal_mm", 20), "field ram.wal_mm"),
        (lambda d: d["probes"][0].__setitem__("y_mm", 0.0), "field probes[0]"),
        (lambda d: d["sensors"][4].__setitem__("z_end_mm", 1500.0), "field sensors[4].z_end_mm"),
        (
            lambda d: d["supports"]["carriages"][1].__setitem__("z_mm", 1300.0),
            "field supports.carriages[1].z_mm",
        ),
        (lambda d: d["materials"].pop("housing"), "field materials.housing"),
        (lambda d: d["materials"]["housing"].pop("cte_per_K"), "field materials.housing.cte_per_K"),
        # the housing's material under both its names: which one holds is not the reader's guess
        (lambda d: d["materials"].__setitem__("steel", dict(d["materials"]["housing"])), "field materials"),
    ],
)
def test_yaml_errors_name_the_file_and_field(tmp_path, edit, field):
    _assert_names_file_and_field(tmp_path, DEFAULT_YAML, edit, field)


def test_the_housings_material_under_its_older_name_is_the_same_machine(tmp_path):
    """Descriptions written before ``materials.housing`` named it ``materials.steel``: read
    as the same machine, down to the key its twin is cached under."""
    from fbgcomp.structure.cache import twin_key

    data = yaml.safe_load(DEFAULT_YAML.read_text())
    data["materials"]["steel"] = data["materials"].pop("housing")
    data["materials"]["steel"]["cte_per_K"] = 23.0e-6  # an aluminium housing
    older = tmp_path / "older.yaml"
    older.write_text(yaml.safe_dump(data))
    data["materials"]["housing"] = data["materials"].pop("steel")
    newer = tmp_path / "newer.yaml"
    newer.write_text(yaml.safe_dump(data))
    a, b = load_machine(older), load_machine(newer)
    assert a == b
    assert a.materials.steel.cte_per_K == 23.0e-6
    assert twin_key(a, 1.0, 1) == twin_key(b, 1.0, 1)
    assert twin_key(a, 1.0, 1) != twin_key(load_machine(DEFAULT_YAML), 1.0, 1)


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
    rank = np.argsort(fe.layer_order(rm.mesh.p, vb.nodal_dofs))  # position of each DOF in layers
    u[free] = fe.Factorised(Kc, order=np.argsort(rank[free])).solve(fc)
    fe_um = 1e3 * tip[0] @ u
    assert fe_um == pytest.approx(_timoshenko_box_um(machine, L, F), rel=0.03)


def _timoshenko_box_um(machine, L, F):
    """Tip deflection (µm) of the default box as a Timoshenko cantilever (bending + shear)."""
    a, b, t = 125.0, 105.0, 20.0
    I = ((2 * a) ** 4 - (2 * b) ** 4) / 12  # noqa: E741 - the second moment of area, as written in mechanics
    E_L, G = 1e3 * machine.materials.cfrp.E_L_GPa, 1e3 * machine.materials.cfrp.G_LT_GPa
    bending = F * L**3 / (3 * E_L * I)
    # Shear compliance from the thin-walled shear flow q(s) on the wall centreline (c = 115 mm).
    c = (a + b) / 2
    s = np.linspace(0, c, 4001)
    q_flange = t * c * s / I  # per unit shear force
    x = np.linspace(-c, c, 8001)
    q_web = q_flange[-1] + t * (c**2 - x**2) / (2 * I)
    shear = F * L * (4 * np.trapezoid(q_flange**2, s) + 2 * np.trapezoid(q_web**2, x)) / (G * t)
    return 1e3 * (bending + shear)


def test_uniform_heating_grows_the_ttp_by_sum_of_cte_times_length(twin, machine):
    """Determinate supports: free expansion; the TTP moves by -(CTE_L z_nut + CTE_steel H) dT."""
    dT = 10.0
    r = twin.static_temperature_response("uniform", dT)
    cf, st = machine.materials.cfrp, machine.materials.steel
    expected_dz_um = (
        -1e3 * dT * (cf.cte_L_per_K * machine.supports.nut.z_mm + st.cte_per_K * machine.housing.height_mm)
    )
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
    twist = (
        fe.elastic.facet_mean_rows(vb, rm.face_facets("+X", 0.0, first))[1]
        - fe.elastic.facet_mean_rows(vb, rm.face_facets("-X", 0.0, first))[1]
    )
    rows = np.vstack([at0, at100[:2] - at0[:2], twist])
    K = K + fe.elastic.spring_matrix(rows, 1e9)
    theta = dT * rm.mesh.p[0] / (2 * rm.half_width_mm)
    u = fe.Factorised(K, order=fe.layer_order(rm.mesh.p, vb.nodal_dofs)).solve(Th @ theta)
    tip_um = 1e3 * fe.elastic.rigid_extension_rows(vb, rm.end_facets(L))[0] @ u
    kappa = -cf.cte_L_per_K * dT / (2 * rm.half_width_mm)  # hotter +X side grows: bends to -X
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
    for axis in range(3):  # small rotations: u = e_axis x r
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
    assert np.allclose(C, C.T, atol=1e-9 * np.abs(C).max())  # Maxwell-Betti
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
        live = span > 1e-6 * np.abs(b).max()  # outputs that move at all in this window
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


def test_the_response_per_expansion_coefficient_sums_to_the_response(twin, fe):
    """The thermal parts of each material's expansion, weighted by the description's
    coefficients, are the twin's own elongations and TTP; weighted by others, those of a twin
    built with them (the temperatures do not depend on the coefficients)."""
    t = np.arange(0.0, 6 * 3600.0, 300.0)
    ambient = 20.0 + 2.0 * np.sin(t / 7200.0)
    Tref = twin.machine.reference_temperature_C
    heat = {twin.machine.thermal.sources[0].name: np.full(t.shape, 150.0)}
    r, parts = twin.thermal_parts(t, ambient, heat=heat, initial_C=Tref)
    assert parts.shape == (t.size, len(fe.elastic.CTE_PARTS), len(twin.sensor_names) + 3)
    want = twin.thermal(t, ambient, heat=heat, initial_C=Tref)
    np.testing.assert_allclose(r.probe_C, want.probe_C, atol=1e-9)
    both = np.hstack([want.sensor_elongation_um, want.ttp_um])
    np.testing.assert_allclose(
        np.einsum("npk,p->nk", parts, twin.cte_per_K), both, atol=1e-9 * np.abs(both).max()
    )
    # another CFRP axial coefficient: a twin built with it answers what the parts say
    d = twin.machine.model_dump()
    d["materials"]["cfrp"]["cte_L_per_K"] = twin.cte_per_K[0] + 1.0e-6
    other = fe.Twin(parse_machine(d), resolution=0.5, cache=False)
    got = other.thermal(t, ambient, heat=heat, initial_C=Tref)
    alpha = twin.cte_per_K + np.array([1.0e-6, 0.0, 0.0])
    both = np.hstack([got.sensor_elongation_um, got.ttp_um])
    np.testing.assert_allclose(np.einsum("npk,p->nk", parts, alpha), both, atol=1e-6 * np.abs(both).max())


@pytest.mark.slow
def test_z_axis_position_moves_the_carriages_and_the_lever_arm(machine, fe):
    """Raising the ram (Z+) brings the carriages closer to the TTP: the tip gets stiffer."""
    low = fe.Twin(machine, resolution=0.4, z_axis_mm=0.0)
    raised = fe.Twin(machine, resolution=0.4, z_axis_mm=300.0)
    assert raised.z_axis_mm == 300.0
    c_low = low.influence.ttp_per_force_um_per_N
    c_raised = raised.influence.ttp_per_force_um_per_N
    assert c_raised[0, 0] < 0.8 * c_low[0, 0]
    assert c_raised[2, 2] == pytest.approx(c_low[2, 2], rel=0.02)  # the nut travels with the ram
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


def test_embedded_paths_bend_with_their_distance_from_the_axis(twin, machine):
    """A grating ``depth_mm`` into the wall reads the bending strain at (half width - depth): away
    from the housing and the carriages, beam theory's ratio to the surface path's; an axial force
    stretches every depth alike; and the thermal rows read the laminate at that depth."""
    hw, wall = machine.ram.outer_width_mm / 2, machine.ram.wall_mm
    base = machine.sensors[0]
    paths = [
        base.model_copy(
            update={"name": f"d{d:g}", "face": "+X", "depth_mm": d, "z_start_mm": 250.0, "z_end_mm": 450.0}
        )
        for d in (0.0, wall / 2, wall)
    ]
    g = twin.path_influence(paths).per_force_um_per_N  # (paths, Fx/Fy/Fz)
    for k, d in enumerate((0.0, wall / 2, wall)):
        assert g[k, 0] / g[0, 0] == pytest.approx((hw - d) / hw, rel=0.04)
        assert g[k, 2] == pytest.approx(g[0, 2], rel=0.01)
    rows = twin.path_influence(paths).temperature_rows
    outer, inner = rows[0].toarray().ravel(), rows[2].toarray().ravel()
    p = twin.mesh.mesh.p
    assert np.allclose(outer @ p[0], hw) and np.allclose(inner @ p[0], hw - wall)


# --------------------------------------------------------------- generalised machine descriptions
RAM2_YAML = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"


@pytest.fixture(scope="session")
def ram2():
    return load_machine(RAM2_YAML)


def test_example_machines_load(ram2):
    assert (
        Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram.yaml"
    ).resolve() == DEFAULT_YAML
    assert [r.face for r in ram2.supports.rails] == ["-Y", "-Y"]
    assert [c.z_mm for c in ram2.supports.carriages] == [1000.0, 1350.0]  # patch centres
    assert ram2.supports.station_ranges_mm() == [(950.0, 1050.0), (1300.0, 1400.0)]
    assert ram2.ttp_z_mm == pytest.approx(-300.0)
    assert [s.gauge_length for s in ram2.sensors] == [600.0] * 4 + [500.0] * 2
    assert ram2.thermal.film_W_per_m2K("-Y") == 4.0
    assert ram2.thermal.film_W_per_m2K("housing_bottom") == 15.0
    assert [h.input_name for h in ram2.thermal.sources] == ["spindle_heat_W", "radiant_W_per_m2"]


def test_built_in_ram_keeps_its_legacy_inputs(machine):
    assert [h.input_name for h in machine.thermal.sources] == ["spindle_heat_W", "radiant_W_per_m2"]
    assert machine.thermal.film_W_per_m2K("top") == machine.thermal.film_outer_W_per_m2K
    assert machine.thermal.film_W_per_m2K("cavity") == machine.thermal.film_inner_W_per_m2K


@pytest.mark.parametrize(
    "edit, field",
    [
        (
            lambda d: d["supports"]["rails"][0].__setitem__("across_mm", [-170.0, -105.0]),
            "field supports.rails[0].across_mm",
        ),
        (
            lambda d: d["supports"]["rails"][0].__setitem__("across_mm", [-105.0, -150.0]),
            "field supports.rails[0].across_mm",
        ),
        (lambda d: d["supports"]["rails"][0].__setitem__("locating", False), "field supports.rails"),
        (lambda d: d["supports"]["rails"][1].__setitem__("face", "+Z"), "field supports.rails[1].face"),
        (lambda d: d["supports"]["rails"][0].__setitem__("floats", "normal"), "field supports.rails[0]"),
        (
            lambda d: d["supports"]["rails"][1].__setitem__("floats", "sideways"),
            "field supports.rails[1].floats",
        ),
        # both rails on -Y floating along its normal: nothing holds the ram along Y
        (
            lambda d: [r.update(locating=False, floats="normal") for r in d["supports"]["rails"]],
            "field supports.rails",
        ),
        (
            lambda d: d["supports"]["carriages"][1].__setitem__("z_range_mm", [1300.0, 1450.0]),
            "field supports.carriages[1].z_mm",
        ),
        (lambda d: d["supports"]["carriages"].pop(), "field supports.carriages"),
        (
            lambda d: d["supports"].__setitem__("carriage_stiffness_N_per_um", "stiff"),
            "field supports.carriage_stiffness_N_per_um",
        ),
        (lambda d: d["supports"]["nut"].__setitem__("constraint", "ring"), "field supports.nut.constraint"),
        (lambda d: d["thermal"]["films_W_per_m2K"].pop("cavity"), "field thermal.films_W_per_m2K.cavity"),
        (
            lambda d: d["thermal"]["films_W_per_m2K"].__setitem__("roof", 3.0),
            "field thermal.films_W_per_m2K.roof.[key]",
        ),
        (lambda d: d["thermal"]["heat_sources"][1].pop("face"), "field thermal.heat_sources[1]"),
        (
            lambda d: d["thermal"]["heat_sources"][0].__setitem__("x_mm", [400.0, 500.0]),
            "field thermal.heat_sources[0]",
        ),
        (  # wholly in the cavity: no material to heat
            lambda d: d["thermal"]["heat_sources"][0].update(
                x_mm=[-100.0, 100.0], y_mm=[-100.0, 100.0], z_mm=[500.0, 600.0]
            ),
            "field thermal.heat_sources[0]",
        ),
        (
            lambda d: d["thermal"]["heat_sources"][1].__setitem__("name", "spindle_heat"),
            "field thermal.heat_sources[1].name",
        ),
        (lambda d: d["tool"].__setitem__("nose_patch_mm", [400.0, 135.0]), "field tool.nose_patch_mm"),
        (lambda d: d["mesh"].__setitem__("element", "hex20"), "field mesh.element"),
        (lambda d: d["sensors"][2].__setitem__("depth_mm", 15.5), "field sensors[2].depth_mm"),
        (lambda d: d["sensors"][0].__setitem__("depth_mm", -1.0), "field sensors[0].depth_mm"),
        # a wall per face: all four faces, each thicker than 0, opposite pairs leaving a cavity,
        # and a grating no deeper than its own face's wall
        (
            lambda d: d["ram"].__setitem__("wall_mm", {"+X": 20.0, "-X": 20.0, "+Y": 12.0}),
            "field ram.wall_mm",
        ),
        (
            lambda d: d["ram"].__setitem__("wall_mm", {"+X": 20.0, "-X": 20.0, "+Y": 12.0, "-Y": 0.0}),
            "field ram.wall_mm",
        ),
        (
            lambda d: d["ram"].__setitem__("wall_mm", {"+X": 160.0, "-X": 140.0, "+Y": 12.0, "-Y": 12.0}),
            "field ram.wall_mm",
        ),
        (
            lambda d: (
                d["ram"].__setitem__("wall_mm", {"+X": 20.0, "-X": 20.0, "+Y": 10.0, "-Y": 12.0}),
                d["sensors"][2].__setitem__("depth_mm", 11.0),  # S3, on +Y
            ),
            "field sensors[2].depth_mm",
        ),
    ],
)
def test_generalised_schema_names_the_bad_field(tmp_path, edit, field):
    _assert_names_file_and_field(tmp_path, RAM2_YAML, edit, field)


def test_rails_on_adjacent_faces_and_more_stations_are_valid(ram2):
    d = ram2.model_dump(mode="json")
    d["supports"]["rails"] = [
        {"face": "-Y", "across_mm": [-150, -105]},
        {"face": "-X", "across_mm": [-150, 150]},
    ]
    d["supports"]["carriages"] = [
        {"name": f"c{i}", "z_range_mm": [z, z + 50]} for i, z in enumerate((700.0, 1000.0, 1300.0))
    ]
    from fbgcomp.structure import parse_machine

    m = parse_machine(d)
    assert len(m.supports.station_ranges_mm()) == 3


def test_a_heat_zone_may_ring_the_cavity_and_heats_the_walls_only(ram2):
    """A data sheet's "nut and motor heat in the top 100 mm of the box": the zone's centre is in
    the air of the cavity, its heat goes into the four walls of that band, all of it."""
    from fbgcomp.structure import parse_machine
    from fbgcomp.structure.mesh import machine_mesh
    from fbgcomp.structure.thermal import assemble_thermal

    d = ram2.model_dump(mode="json")
    d["thermal"]["heat_sources"].append(
        {
            "name": "nut_motor",
            "kind": "volume",
            "x_mm": [-150, 150],
            "y_mm": [-150, 150],
            "z_mm": [1300, 1400],
        }
    )
    m = parse_machine(d)
    assert [h.input_name for h in m.thermal.sources][-1] == "nut_motor_W"
    rm = machine_mesh(m, 0.5, m.supports.z_axis_mm)
    _, _, B = assemble_thermal(rm, m)
    col = B[:, -1]
    assert col.sum() == pytest.approx(1.0)
    x, y, z = rm.mesh.p
    heated = col > 0
    assert z[heated].min() == pytest.approx(1300.0) and z[heated].max() == pytest.approx(1400.0)
    in_cavity = (np.abs(x) < 135.0 - 1e-6) & (np.abs(y) < 135.0 - 1e-6)
    assert not np.any(heated & in_cavity)
    for face in (x > 150 - 15, x < -150 + 15, y > 150 - 15, y < -150 + 15):  # every wall gets its share
        assert col[heated & face].sum() > 0.15


def _ram2_with_walls(walls, **cfrp):
    data = yaml.safe_load(RAM2_YAML.read_text())
    data["ram"]["wall_mm"] = walls
    data["materials"]["cfrp"].update(cfrp)
    return parse_machine(data, RAM2_YAML)


def test_a_wall_per_face_of_one_thickness_is_the_uniform_box(ram2, fe):
    """``wall_mm`` per face, every face 15 mm, is ram2's box to the last node and facet; a probe
    in a thicker wall is in the structure, one where that wall would be cavity is not."""
    from fbgcomp.structure.mesh import machine_mesh

    same = _ram2_with_walls(dict.fromkeys(("+X", "-X", "+Y", "-Y"), 15.0))
    a, b = machine_mesh(ram2), machine_mesh(same)
    assert np.array_equal(a.mesh.p, b.mesh.p) and np.array_equal(a.mesh.t, b.mesh.t)
    assert a.cavity_mm == b.cavity_mm == (-135.0, 135.0, -135.0, 135.0)
    for facets in ("outer_facets", "inner_facets"):
        assert np.array_equal(getattr(a, facets)(), getattr(b, facets)())
    thick = _ram2_with_walls({"+X": 30.0, "-X": 15.0, "+Y": 15.0, "-Y": 15.0})
    assert thick.contains_point(125.0, 0.0, 700.0) and not ram2.contains_point(125.0, 0.0, 700.0)
    assert not thick.contains_point(-125.0, 0.0, 700.0)
    rm = machine_mesh(thick)
    assert rm.cavity_mm == (-135.0, 120.0, -135.0, 135.0)
    cells = rm.mesh.p[:, rm.mesh.t].mean(axis=1)
    in_x_walls = (cells[2] > 0) & (np.abs(cells[1]) < 135.0)
    assert cells[0, in_x_walls].max() > 120.0 and not np.any(
        (cells[0] > 120.0) & (cells[0] < 135.0) & ~in_x_walls & (cells[2] > 0) & (np.abs(cells[1]) < 135.0)
    )


@pytest.mark.parametrize("thick_face, centroid_x_mm", [("+X", 17.65), ("-X", -17.65)])
def test_a_thicker_wall_moves_the_bending_axis_to_the_sections_centroid(fe, thick_face, centroid_x_mm):
    """The built-in box with one X wall twice the others' (40 against 20 mm) bends under Fx about
    its section's centroid, 17.65 mm towards the thick wall: the gratings of the two X faces,
    125 mm either side of the axis, read a strain that vanishes there, and the Y faces' gratings
    on the axis read the strain 17.65 mm from it. Plane sections hold where the walls are stiff
    in shear (a quasi-isotropic laminate here); a CFRP 16 times softer in shear than along its
    fibres shear-lags the flange centres (ram2's laminate with its +X wall doubled: the X
    gratings' zero at 35 mm against a centroid at 24.4, resolution 1 and 2, one-off, 2026-12-08)."""
    from fbgcomp.kinematics import ram_centroid_mm

    data = yaml.safe_load(DEFAULT_YAML.read_text())
    data["ram"]["wall_mm"] = {"+X": 20.0, "-X": 20.0, "+Y": 20.0, "-Y": 20.0} | {thick_face: 40.0}
    data["materials"]["cfrp"].update(E_L_GPa=120.0, E_T_GPa=120.0, G_LT_GPa=46.0, nu_LT=0.3, nu_TT=0.3)
    m = parse_machine(data, DEFAULT_YAML)
    assert ram_centroid_mm(m) == pytest.approx((centroid_x_mm, 0.0), abs=0.01)
    r = fe.Twin(m, resolution=0.5, reduce_thermal=False, cache=False).static([1000.0, 0.0, 0.0])
    e = dict(zip(r.sensor_names, r.sensor_elongation_um[0], strict=True))
    hw = m.ram.outer_width_mm / 2
    curvature = (e["S1"] - e["S2"]) / (2 * hw)  # µm per mm across the section
    zero_mm = hw - e["S1"] / curvature
    assert zero_mm == pytest.approx(centroid_x_mm, abs=0.75)
    assert e["S3"] == pytest.approx(-curvature * centroid_x_mm, rel=0.04)
    assert e["S4"] == pytest.approx(-curvature * centroid_x_mm, rel=0.04)


def test_the_beam_section_of_uneven_walls_is_the_integral_over_its_area(ram2):
    """The kinematic chain's ram section (centroid, second moments about it, webs' shear area)
    against a direct sum over a 0.5 mm grid of the section with its walls."""
    from fbgcomp.kinematics import ram_centroid_mm, ram_section

    m = _ram2_with_walls({"+X": 30.0, "-X": 12.0, "+Y": 22.0, "-Y": 9.0})
    x_lo, x_hi, y_lo, y_hi = m.ram.cavity_mm
    c = np.arange(-150.0, 150.0, 0.5) + 0.25
    gx, gy = np.meshgrid(c, c, indexing="ij")
    solid = ~((gx > x_lo) & (gx < x_hi) & (gy > y_lo) & (gy < y_hi))
    dA = 0.25
    area = solid.sum() * dA
    xc, yc = (gx[solid].sum() * dA / area, gy[solid].sum() * dA / area)
    assert ram_centroid_mm(m) == pytest.approx((xc, yc), abs=1e-6)
    sec = ram_section(m)
    E = 1e3 * m.materials.cfrp.E_L_GPa
    i_x = ((gy[solid] - yc) ** 2).sum() * dA + solid.sum() * dA * 0.5**2 / 12
    i_y = ((gx[solid] - xc) ** 2).sum() * dA + solid.sum() * dA * 0.5**2 / 12
    assert sec.EI_x / E == pytest.approx(i_x, rel=1e-9)
    assert sec.EI_y / E == pytest.approx(i_y, rel=1e-9)
    assert sec.GA_x == pytest.approx(1e3 * m.materials.cfrp.G_LT_GPa * (22.0 + 9.0) * 300.0)


@pytest.fixture(scope="session")
def ram2_twin(ram2, fe):
    return fe.Twin(ram2, resolution=0.5)


@pytest.mark.slow
def test_ram2_supports_hold_the_carriage_patches(ram2_twin, ram2):
    """Every node of the four carriage patches is held in Y; the locating strip's also in X; no
    node behind the face is held (the facets' assembled trace leaves round-off there, which once
    held the wall through its thickness: ram6's lateral compliance came out 25 % stiff)."""
    rm, vb = ram2_twin.mesh, ram2_twin._vbasis
    held = np.zeros(vb.N)
    held[ram2_twin.support_rows_mm.indices] = 1.0
    p = rm.mesh.p
    on_face = np.abs(p[1] + 150.0) < 1e-6
    in_station = ((p[2] >= 950 - 1e-6) & (p[2] <= 1050 + 1e-6)) | (p[2] >= 1300 - 1e-6)
    strip_loc = on_face & in_station & (p[0] <= -105 + 1e-6)
    strip_float = on_face & in_station & (p[0] >= 105 - 1e-6)
    assert held[vb.nodal_dofs[1, strip_loc | strip_float]].all()
    assert held[vb.nodal_dofs[0, strip_loc]].all()
    assert not held[vb.nodal_dofs[0, strip_float]].any()
    assert not held[vb.nodal_dofs[:2, ~on_face]].any()
    top = np.abs(p[2] - 1400.0) < 1e-6
    assert held[vb.nodal_dofs[2, top]].all() and held[vb.nodal_dofs[2]].sum() == top.sum()


@pytest.mark.slow
def test_uniform_warming_moves_ram2_away_from_its_reference_face_and_locating_rail(ram2_twin, ram2):
    """Rails on -Y, locating rail at x <= -105: the box grows towards +Y and +X (README sec. 4)."""
    dT = 10.0
    r = ram2_twin.static_temperature_response("uniform", dT)
    dx, dy, dz = r.ttp_um
    cte_T = ram2.materials.cfrp.cte_T_per_K
    assert dy > 0 and dx > 0
    # The axis is half a depth from the reference face: it moves by about cte_T dT 150 mm.
    assert dy == pytest.approx(1e3 * cte_T * dT * 150.0, rel=0.05)
    assert dx == pytest.approx(1e3 * cte_T * dT * 127.5, rel=0.15)  # strip centre 127.5 mm off axis
    cf, st = ram2.materials.cfrp, ram2.materials.steel
    assert dz == pytest.approx(-1e3 * dT * (cf.cte_L_per_K * 1400 + st.cte_per_K * 180), rel=0.01)


def _opposite_rails(ram2, floats):
    """ram2 guided on two opposite faces: a locating rail on +Y, the other on -Y floating
    ``floats`` (across the face, or along its normal: the carriages let the box grow), or
    locating too (``floats`` None)."""
    d = ram2.model_dump(mode="json")
    minus = {"face": "-Y", "across_mm": [-40.0, 40.0]}
    minus |= {"floats": floats} if floats else {"locating": True}
    d["supports"]["rails"] = [{"face": "+Y", "across_mm": [-40.0, 40.0], "locating": True}, minus]
    return parse_machine(d)


@pytest.mark.slow
def test_a_rail_floating_along_its_normal_lets_the_box_grow_towards_it(ram2, fe):
    """Rails on opposite faces, the -Y one floating along its normal: its carriage patches hold
    u_x only, and a uniform warming moves the axis away from the +Y locating face (dy < 0), not
    in X. The same rail holding its normal and X as well (a second locating rail) pins the box's
    width at both faces, and the two faces' symmetry leaves the axis where it was. (Holding the
    normal alone on -Y, floating across, is not symmetric: the +Y strip's transverse expansion
    is held in X and the -Y strip's is not, and that bends the box: +7.9 µm of dy.)"""
    free = fe.Twin(_opposite_rails(ram2, "normal"), resolution=0.5)
    rm, vb = free.mesh, free._vbasis
    held = np.zeros(vb.N)
    held[free.support_rows_mm.indices] = 1.0
    p = rm.mesh.p
    in_station = ((p[2] >= 950 - 1e-6) & (p[2] <= 1050 + 1e-6)) | (p[2] >= 1300 - 1e-6)
    strip = in_station & (np.abs(p[0]) <= 40 + 1e-6)
    minus_y, plus_y = strip & (np.abs(p[1] + 150) < 1e-6), strip & (np.abs(p[1] - 150) < 1e-6)
    assert minus_y.any() and plus_y.any()
    assert held[vb.nodal_dofs[0, minus_y | plus_y]].all() and held[vb.nodal_dofs[1, plus_y]].all()
    assert not held[vb.nodal_dofs[1, minus_y]].any()

    dx, dy, _ = free.static_temperature_response("uniform", 10.0).ttp_um
    assert dy < -10.0 and abs(dx) < 0.05 * abs(dy), (dx, dy)
    pinned = fe.Twin(_opposite_rails(ram2, None), resolution=0.5)
    dy_pinned = pinned.static_temperature_response("uniform", 10.0).ttp_um[1]
    assert abs(dy_pinned) < 1e-3 * abs(dy), (dy_pinned, dy)


@pytest.mark.slow
def test_heat_sources_drive_the_twin_by_name_or_legacy_argument(ram2_twin):
    t = np.arange(0.0, 3601.0, 60.0)
    spindle = np.where(t > 300, 120.0, 0.0)
    radiant = np.where(t > 900, 90.0, 0.0)
    a = ram2_twin.thermal(t, 22.0, spindle, radiant, initial_C=22.0)
    b = ram2_twin.thermal(
        t, 22.0, initial_C=22.0, heat={"spindle_heat": spindle, "radiant_W_per_m2": radiant}
    )
    assert np.array_equal(a.ttp_um, b.ttp_um)
    assert ram2_twin.input_names == ("ambient_C", "spindle_heat_W", "radiant_W_per_m2")
    # Spindle heat warms the housing's -X face probe; the radiant load only the +X side of the box.
    assert a.probe("T_flange")[-1] > 22.1
    only_rad = ram2_twin.thermal(t, 22.0, initial_C=22.0, heat={"radiant": radiant})
    s1, s2 = only_rad.sensor_temperature_C[-1, :2]
    assert s1 > s2 + 0.05
    with pytest.raises(ValueError, match="unknown heat source"):
        ram2_twin.thermal(t, 22.0, heat={"lamp": radiant})


def test_films_per_surface_reproduce_the_outer_inner_pair(machine, fe):
    """Listing every surface with the legacy outer/inner values assembles the same model."""
    from fbgcomp.structure import parse_machine, thermal
    from fbgcomp.structure.mesh import machine_mesh

    th = machine.thermal
    d = machine.model_dump(mode="json")
    d["thermal"]["films_W_per_m2K"] = {
        s: (th.film_inner_W_per_m2K if s == "cavity" else th.film_outer_W_per_m2K)
        for s in ("+X", "-X", "+Y", "-Y", "cavity", "top", "housing_sides", "housing_bottom")
    }
    d["thermal"]["films_W_per_m2K"]["-Y"] = 2 * th.film_outer_W_per_m2K
    rm = machine_mesh(machine, 0.4)
    K0, _, B0 = thermal.assemble_thermal(rm, machine)
    K1, _, B1 = thermal.assemble_thermal(rm, parse_machine(d))
    extra = K1 - K0
    # Only the -Y face's film changed: the difference is one more film on that face.
    y = rm.mesh.p[1]
    rows = np.unique(extra.tocoo().row[np.abs(extra.tocoo().data) > 1e-15])
    assert len(rows) and np.all(np.abs(y[rows] + rm.half_depth_mm) < 1e-6)
    assert np.allclose(B1[:, 1:], B0[:, 1:])


def test_incompatible_modes_remove_the_bending_lock_of_the_coarse_cantilever(machine, fe):
    """Same coarse mesh: plain hex8 is too stiff in bending + shear, hex8i within 2 %."""
    from skfem import condense

    L, F = 2400.0, 1000.0
    rm = _box(fe, machine, L, 0.4)
    tips = {}
    for incompatible in (False, True):
        vb, _, K, _ = fe.elastic.assemble_box_elasticity(
            rm, machine.materials.cfrp, machine.materials.steel, incompatible
        )
        tip = fe.elastic.rigid_extension_rows(vb, rm.end_facets(L))
        clamped = vb.get_dofs(lambda x: np.abs(x[2]) < 1e-6).all()
        Kc, fc, _, free = condense(K, tip[0] * F, D=clamped)
        u = np.zeros(vb.N)
        rank = np.argsort(fe.layer_order(rm.mesh.p, vb.nodal_dofs))
        u[free] = fe.Factorised(Kc, order=np.argsort(rank[free])).solve(fc)
        tips[incompatible] = 1e3 * tip[0] @ u
    theory_um = _timoshenko_box_um(machine, L, F)
    assert tips[True] == pytest.approx(theory_um, rel=0.02)
    assert abs(tips[False] / theory_um - 1) > 2 * abs(tips[True] / theory_um - 1)


def test_closed_form_box_assembly_matches_the_skfem_forms(machine, fe):
    """The vectorised hex8 assembly (closed-form box elements) equals scikit-fem's weak forms to
    round-off, on the housing + ram mesh (both materials), numbered the same."""
    from fbgcomp.structure.mesh import machine_mesh

    rm = machine_mesh(machine, 0.4)
    mats = machine.materials
    vb1, _, K1, T1 = fe.elastic.assemble_elasticity_forms(rm, mats.cfrp, mats.steel)
    vb2, _, K2, T2 = fe.elastic.assemble_elasticity(rm, mats.cfrp, mats.steel)
    assert fe.elastic._box_geometry(rm.mesh.p, rm.mesh.t)[0] is not None  # the fast path ran
    assert np.array_equal(vb1.nodal_dofs, vb2.nodal_dofs)
    assert K1.shape == K2.shape and T1.shape == T2.shape
    assert abs(K1 - K2).max() <= 1e-13 * abs(K1).max()
    assert abs(T1 - T2).max() <= 1e-13 * abs(T1).max()
    # A mesh that is not made of boxes takes the forms: shear one node of the grid.
    p = rm.mesh.p.copy()
    p[0, 0] += 0.1
    assert fe.elastic._box_geometry(p, rm.mesh.t)[0] is None


def test_block_tridiagonal_factor_solves_like_the_banded_one(twin, fe):
    """The elastic matrix, layer-ordered, is block tridiagonal: its block factor (the twin's)
    and the banded factor give the same solutions to round-off, for one or many vectors."""
    K = twin._K_elastic
    order = fe.layer_order(twin.mesh.mesh.p, twin._vbasis.nodal_dofs)
    blocked = fe.Factorised(K, order=order, blocked=True)
    banded = fe.Factorised(K, order=order)
    assert blocked.backend.startswith("block") and banded.backend.startswith("banded")
    assert twin._elastic.backend.startswith("block")
    b = np.random.default_rng(3).standard_normal((K.shape[0], 4))
    for rhs in (b, b[:, 0], twin._R.T):
        x, xb = blocked.solve(rhs), banded.solve(rhs)
        assert x.shape == xb.shape
        assert np.abs(x - xb).max() <= 1e-8 * np.abs(xb).max()
        assert np.abs(K @ x - rhs).max() <= 1e-9 * np.abs(rhs).max()
    # a matrix without block structure beyond its band keeps the banded factor
    import scipy.sparse as sp

    T = sp.diags([-np.ones(99), 4 * np.ones(100), -np.ones(99)], [-1, 0, 1]).tocsr()
    assert fe.Factorised(T, blocked=True).backend.startswith("banded")


def test_a_ram_on_rails_takes_the_block_factor_too(fe):
    """ram2's description (rails on one face, a solid steel housing): its layers' blocks cost a
    little more flops than its band (ratio 1.14 on this mesh, 1.12 on its own), and the block
    factor still runs 1.2-1.5x faster (benchmarks/bench_factor.py); the rule before (0.8) left it
    banded. Same solutions to round-off."""
    ram2 = fe.Twin(
        load_machine(Path(__file__).resolve().parents[1] / "examples/machines/ram2.yaml"), resolution=0.5
    )
    assert ram2._elastic.backend.startswith("block")
    K = ram2._K_elastic
    order = fe.layer_order(ram2.mesh.mesh.p, ram2._vbasis.nodal_dofs)
    banded = fe.Factorised(K, order=order)
    assert banded.backend.startswith("banded")
    x, xb = ram2._elastic.solve(ram2._R.T), banded.solve(ram2._R.T)
    assert np.abs(x - xb).max() <= 1e-8 * np.abs(xb).max()
