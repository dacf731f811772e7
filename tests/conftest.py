"""Session-wide test set-up: the twin cache folder of the session, the shared state the tests
build once (session fixtures, never module-level caches), and the ``slow`` marker of the tests
that take longer than a fast check should (``scripts/test -m "not slow"`` leaves them out)."""

import os
import shutil
import sys
import tempfile

import pytest

sys.path.insert(0, os.path.dirname(__file__))


# The twin cache (fbgcomp.structure.cache) of the whole run: a fresh folder the controller makes
# before the xdist workers start (they and every CLI subprocess inherit the variable), removed at
# the end, so tests never read nor write the user's cache (~/.cache/fbgcomp) and start cold. One
# folder for every worker, with room for the suite's ~35 twins: each is built once in the run
# (the build lock makes a second worker wait for the first's), not once per worker and again
# after the user's limit of 8 entries pushed it out (87 builds, ~400 CPU-seconds, before).
_CACHE_ENV = {"FBGCOMP_CACHE_MAX_ENTRIES": "64", "FBGCOMP_CACHE_MAX_BYTES": str(8 << 30)}


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # an xdist worker: the controller's folder, inherited
        return
    folder = tempfile.mkdtemp(prefix="fbgcomp-test-cache-")
    config._fbgcomp_env = {k: os.environ.get(k) for k in ("FBGCOMP_CACHE_DIR", *_CACHE_ENV)}
    config._fbgcomp_cache = folder
    os.environ.update({"FBGCOMP_CACHE_DIR": folder, **_CACHE_ENV})


def pytest_unconfigure(config):
    folder = getattr(config, "_fbgcomp_cache", None)
    if folder is None:
        return
    for k, v in config._fbgcomp_env.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def runtime_model_and_campaign(tmp_path_factory):
    """(model.json, campaign folder) of the runtime tests, built once per session in
    ``<basetemp>/runtime`` (test_runtime_support.model_and_campaign)."""
    from test_runtime_support import model_and_campaign

    return model_and_campaign(tmp_path_factory.getbasetemp() / "runtime")


@pytest.fixture(scope="session")
def runtime_model_and_arrays(runtime_model_and_campaign):
    """(model, time s, wavelengths nm, temperatures °C) of :func:`runtime_model_and_campaign`:
    the model loaded from its file and the campaign's aligned arrays in the model's order
    (test_runtime_support.model_and_arrays). Shared by the whole session: the arrays are
    read-only, so a test that changes them works on its own copy."""
    from test_runtime_support import model_and_arrays

    model, time_s, w, t = model_and_arrays(*runtime_model_and_campaign)
    for a in (time_s, w, t):
        a.flags.writeable = False
    return model, time_s, w, t


@pytest.fixture(scope="session")
def ram2_default_model():
    """The default fit on ram2 as the README gives it, built once per session: ``fbgcomp fit
    thermal_a static_xyz --machine examples/machines/ram2.yaml`` (the physical model, its thermal
    map learnt from the twin of the description). Tests read it; none may change it."""
    from pathlib import Path

    from fbgcomp.models.physical import PhysicalModel
    from fbgcomp_testing import read_ram2

    r = read_ram2("thermal_a", "static_xyz")
    machine = Path(__file__).resolve().parents[1] / "examples" / "machines" / "ram2.yaml"
    return PhysicalModel(machine=machine).fit([r["thermal_a"], r["static_xyz"]])


# Slow tests of the files that do not mark them with @pytest.mark.slow themselves: a whole file,
# or a test with all its parametrisations. The seconds: setup + call, all cases, as measured
# per file (pytest --durations) on the shared 2-core machine under load, November 2026.
SLOW = {
    # whole files: subprocesses, servers, fits on long campaigns; few or no fast tests
    "tests/test_compare.py": 189,
    "tests/test_dataset.py": 23,
    "tests/test_distributed.py": 74,
    "tests/test_import.py": 48,
    "tests/test_models.py": 154,
    "tests/test_predictor_compiled.py": 2,
    "tests/test_runtime_e2e.py": 15,
    "tests/test_runtime_envelope.py": 9,
    "tests/test_runtime_fastpath.py": 7,
    "tests/test_runtime_live_inputs.py": 76,
    "tests/test_runtime_log.py": 15,
    "tests/test_runtime_modbus.py": 25,
    "tests/test_runtime_modehop.py": 57,
    "tests/test_runtime_opcua.py": 47,
    "tests/test_runtime_opcua_cnc_form.py": 29,
    "tests/test_runtime_output.py": 16,
    "tests/test_runtime_refgratings.py": 24,
    "tests/test_runtime_trust.py": 10,
    # single tests of files that are otherwise fast
    "tests/test_campaign.py::test_a_link_to_another_file_never_has_its_content_echoed": 8.7,
    "tests/test_campaign.py::test_a_million_column_header_is_refused_in_seconds_by_inspect_and_fit": 7.3,
    "tests/test_campaign.py::test_arbitrary_bytes_in_fbg_csv_give_a_campaign_or_an_input_error": 3.9,
    "tests/test_campaign.py::test_parser_survives_garbage_in_a_cell_or_header": 2.7,
    "tests/test_campaign.py::test_reader_survives_arbitrary_file_contents": 1.6,
    "tests/test_campaign.py::test_streamed_blocks_read_exactly_what_a_whole_read_does": 7.7,
    "tests/test_campaign.py::test_the_column_cap_is_documented_and_exact": 1.0,
    "tests/test_campaign.py::test_write_read_round_trip": 5.7,
    # the first two: every user of the physical model the module builds once (59 s)
    "tests/test_model_boundary.py::test_a_physical_model_whose_shapes_disagree_is_refused_on_loading": 60.7,
    "tests/test_model_boundary.py::test_any_mutation_of_a_physical_model_loads_or_is_an_input_error": 4.0,
    "tests/test_model_boundary.py::test_any_mutation_of_a_regression_model_loads_or_is_an_input_error": 7.4,
    "tests/test_model_boundary.py::test_any_mutation_of_a_kinematic_model_loads_or_is_an_input_error": 1.3,
    "tests/test_model_types.py::test_calibrated_closure_recovers_unseen_x_loads_from_y_loads": 64.9,
    "tests/test_model_types.py::test_calibrated_factors_are_near_one_where_the_beam_closure_holds": 13.1,
    "tests/test_model_types.py::test_calibrated_without_loads_keeps_the_nominal_closure": 24.8,
    "tests/test_model_types.py::test_cli_compare_writes_ranked_tables": 13.4,
    "tests/test_model_types.py::test_cli_fit_model_types_and_validate_prints_coverage": 40.7,
    "tests/test_model_types.py::test_hybrid_keeps_the_physics_where_regression_cannot_extrapolate": 1.9,
    "tests/test_model_types.py::test_kinematic_model_needs_no_campaign_and_follows_z": 6.0,
    "tests/test_model_types.py::test_v1_model_file_is_migrated": 1.1,
    "tests/test_physical.py::test_a_force_the_training_never_applied_is_read_over_the_trained_range": 20.8,
    # with these three, every user of the twin-fitted model of the module is slow (12-20 s to fit)
    "tests/test_physical.py::test_default_beats_the_simplest_physical_model_on_dz": 0.5,
    "tests/test_physical.py::test_interval_is_the_interferometers_at_rest_and_grows_with_the_thermal_state": 0.9,
    "tests/test_physical.py::test_a_grating_that_jumps_alone_is_not_read_as_a_load": 0.0,
    "tests/test_physical.py::test_a_lost_grating_keeps_the_load_part": 1.1,
    "tests/test_physical.py::test_calibrated_map_streams_and_round_trips": 1.5,
    "tests/test_physical.py::test_model_file_round_trip_and_runtime_predictor": 1.5,
    "tests/test_physical.py::test_static_load_is_read_through_the_load_signature": 1.3,
    "tests/test_physical.py::test_the_served_correction_does_not_depend_on_frame_rate_or_batching": 34.4,
    "tests/test_physical.py::test_the_vectorised_steady_stretches_equal_the_per_frame_recursion": 51.9,
    "tests/test_physical.py::test_twin_learned_thermal_map_meets_the_lateral_targets": 20.3,
    "tests/test_runtime_hyperion.py::test_temporary_faults_end_and_garbage_makes_the_source_reconnect": 1.0,
    "tests/test_runtime_pipeline.py::test_model_reload_keeps_the_re_admission_check": 1.8,
    "tests/test_runtime_ram2.py": 71.0,
    "tests/test_heat_inputs.py::test_the_measured_power_takes_dz_below_2_um_on_ram2_served_by_the_runtime": 40.0,
    "tests/test_heat_inputs.py::test_a_model_with_heat_inputs_round_trips_and_refuses_a_campaign_without_them": 5.0,
    "tests/test_heat_inputs.py::test_heat_inputs_can_be_left_out": 8.0,
    "tests/test_heat_inputs.py::test_the_thermal_observer_reads_the_measured_power": 54.0,
    "tests/test_heat_inputs.py::test_fit_and_validate_with_heat_csv_through_the_console": 28.0,
    "tests/test_heat_inputs.py::test_serve_replays_the_power_logs_it_and_exports_it_as_heat_csv": 20.0,
    "tests/test_heat_inputs.py::test_serve_reads_the_spindle_power_over_opcua_and_holds_when_it_goes_stale": 60.0,
    "tests/test_physical.py::test_a_fallback_holds_back_what_its_lost_gratings_told_the_full_map": 16.0,
    # users of the session's ram2 default fit (17 s to build when they run first)
    "tests/test_physical.py::test_the_lateral_correction_at_a_z_the_training_never_saw_is_held_back": 1.4,
    "tests/test_physical.py::test_the_runtime_holds_the_lateral_correction_at_a_live_z_the_training_never_saw": 1.6,
}


@pytest.hookimpl(trylast=True)  # after pytest-xdist's, which names each grouped test's group
def pytest_collection_modifyitems(config, items):
    # --dist loadgroup sends the tests of one xdist_group to one worker (LinuxCNC, a machine-wide
    # resource; a module's costly fixtures, built once). pytest 9.2 dropped the node-id suffix
    # pytest-xdist 3.8 groups by, and every group was spread over the workers without a word
    # (pytest-dev/pytest-xdist#1386; pyproject.toml pins pytest below 9.2): refuse to run so
    if getattr(config.option, "loadgroup", False):
        lost = [i.nodeid for i in items if i.get_closest_marker("xdist_group") and "@" not in i.nodeid]
        if lost:
            msg = (
                f"--dist loadgroup does not group {lost[0]} (and {len(lost) - 1} more) with this pytest "
                "and pytest-xdist (pytest-dev/pytest-xdist#1386): install the versions pyproject.toml names"
            )
            print(msg, file=sys.stderr)  # a worker's error reaches the console only as xdist's own
            raise pytest.UsageError(msg)

    # the slow tests first (a stable sort: each file's tests keep their order, and a file's
    # module-scoped fixture stays built once where its tests are all slow or all fast, as in
    # test_dashboard, test_dashboard_drift and test_distributed): pytest-xdist hands the tests out
    # in this order, so the workers end on short tests together. In collection order the long
    # ones came last (test_ram3..7, test_readme, test_runtime_*) and one worker ran alone for the
    # last ~2 minutes (CPU sampled every 5 s in CI of 2026-12-07: 43-56 % busy)
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)

    # a renamed test would silently join the fast subset: say so
    used, collected = config.stash.get(_SLOW_SEEN, (set(), set()))
    stale = [k for k in SLOW if k not in used and k.partition("::")[0] in collected]
    if stale:
        config.issue_config_time_warning(
            pytest.PytestConfigWarning(f"tests/conftest.py SLOW names no collected test: {stale}"), 2
        )


# (SLOW keys matched, test files collected), as each test is collected
_SLOW_SEEN = pytest.StashKey[tuple[set, set]]()


# as each test is collected, before the mark plugin's -m and -k deselect it: -m "not slow" leaves
# out the tests SLOW names, and the stale check sees every test collected, not only those -k kept
# (marked in pytest_collection_modifyitems after the deselection before, the fast subset held
# every SLOW test, and -k warned of stale names that were only deselected)
def pytest_itemcollected(item):
    used, collected = item.config.stash.setdefault(_SLOW_SEEN, (set(), set()))
    path, _, name = item.nodeid.partition("::")
    collected.add(path)
    for key in (path, f"{path}::{name.split('[', 1)[0].split('@', 1)[0]}"):
        if key in SLOW:
            item.add_marker(pytest.mark.slow)
            used.add(key)
