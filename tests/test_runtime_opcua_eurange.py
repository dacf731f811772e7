"""The EURange of each axis's ``Correction<A>_um`` on a real ``fbgcomp serve``'s OPC UA server
is the correction cap serve runs with (``pipeline.max_correction_um``, tightened per axis by
the model file's own bound), read by a real asyncua client (Basic256Sha256, trusted, with a
user) as an integrator's client reads it: the ``EURange`` and ``EngineeringUnits`` properties of
the AnalogItemType variables."""

from __future__ import annotations

import asyncio

import fbgcomp_testing
from test_runtime_support import secure_client, serve_with_simulator

ENV = {"FBGCOMP_OPCUA_USER": "operator", "FBGCOMP_OPCUA_PASSWORD": "eurange-pass-1"}
CAPS = (12.5, 30.0, 0.0)  # µm per axis; 0: no cap of serve's own on Z (the model's applies)


async def read_analog(url, state, trust_dir, names):
    """(EURange, EngineeringUnits) of ``FbgComp.<name>`` for each of ``names``, found by
    browsing the node's properties; the client's certificate is put in serve's trust list."""
    from asyncua import ua

    from fbgcomp.runtime.trust import add_certificate

    client = await secure_client(url, state, ENV["FBGCOMP_OPCUA_USER"], ENV["FBGCOMP_OPCUA_PASSWORD"])
    add_certificate(state / "client_cert.der", trust_dir)
    out = {}
    async with client:
        for name in names:
            node = client.get_node(ua.NodeId(f"FbgComp.{name}", 2))
            assert await node.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogItemType), name
            rng = await (await node.get_child(["0:EURange"])).read_value()
            eu = await (await node.get_child(["0:EngineeringUnits"])).read_value()
            out[name] = (rng, eu)
    return out


def test_each_axis_correction_eurange_is_the_cap_serve_runs_with(tmp_path, runtime_model_and_campaign):
    fbgcomp_testing.require("asyncua")
    from asyncua import ua

    from fbgcomp.models.registry import load_model

    model_path, campaign = runtime_model_and_campaign
    own = load_model(model_path).max_correction_um  # the model file's bound, per axis
    # the configured caps are tighter than the model's on X and Y, so they are the ones in force
    assert own is not None and own[0] > CAPS[0] and own[1] > CAPS[1], own
    expected = {"X": CAPS[0], "Y": CAPS[1], "Z": own[2]}
    toml = "[pipeline]\nmax_correction_um = [" + ", ".join(str(c) for c in CAPS) + "]\n"
    names = [f"Correction{a}_um" for a in "XYZ"] + ["PredictedDeviationX_um"]
    with serve_with_simulator(tmp_path, toml, model_path, campaign, ENV) as run:
        got = asyncio.run(
            read_analog(run.url, tmp_path / "client", tmp_path / "state" / "opcua" / "trusted", names)
        )
        assert run.serve.poll() is None  # serve ran on while the client read
    for a, cap in expected.items():
        rng, eu = got[f"Correction{a}_um"]
        assert isinstance(rng, ua.Range), (a, rng)
        assert (rng.Low, rng.High) == (-cap, cap), (a, rng)
        assert isinstance(eu, ua.EUInformation), (a, eu)
        assert eu.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
        assert eu.UnitId == 13384 and eu.DisplayName.Text == "µm", (a, eu)  # UNECE "4H"
    # the per-axis ranges are the correction's only: the prediction keeps its default
    rng, _ = got["PredictedDeviationX_um"]
    assert (rng.Low, rng.High) == (-1000.0, 1000.0)


def test_the_expected_caps_are_what_the_pipeline_runs_with(runtime_model_and_campaign):
    """The expectation above is the pipeline's own arithmetic, not only the test's: the cap in
    force is the configured one, tightened by the model's, 0 meaning none of serve's own."""
    from fbgcomp.models.registry import load_model
    from fbgcomp.runtime.pipeline import Pipeline, PipelineConfig

    model = load_model(runtime_model_and_campaign[0])
    cap = Pipeline(model, PipelineConfig(max_correction_um=CAPS)).max_correction_um
    assert list(cap) == [CAPS[0], CAPS[1], model.max_correction_um[2]]
