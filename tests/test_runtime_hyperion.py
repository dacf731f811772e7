"""Hyperion protocol codec, client and the simulated instrument, over real loopback sockets."""

import asyncio
import struct

import numpy as np
import pytest

from fbgcomp.errors import InputError
from fbgcomp.runtime import hyperion
from fbgcomp.runtime.simulator import SignalTable, SimConfig, SimulatedHyperion, parse_fault
from fbgcomp.runtime.sources import PeakMapper


def _table():
    t = np.arange(0.0, 60.0, 0.5)
    wl = 1530.0 + 5.0 * np.arange(4)[None, :] + 0.01 * np.sin(t[:, None] / 7 + np.arange(4))
    return SignalTable(t, wl, ["S1", "S2", "S3", "S4"])


def test_peak_frame_layout_matches_the_protocol_byte_for_byte():
    frame = hyperion.encode_peak_frame(42, 1700000000.25, np.array([2, 1]),
                                       np.array([1530.5, 1535.25, 1540.125]))
    status, rtype, msg_len, content_len = struct.unpack_from("<BBHI", frame, 0)
    assert (status, rtype, msg_len) == (0, 0, 0) and content_len == len(frame) - 8
    length, version, _, serial, t_int, t_frac = struct.unpack_from("<HHIQII", frame, 8)
    assert length == 24 + 2 * 2 and serial == 42
    assert t_int == 1700000000 and t_frac == 250_000_000
    assert struct.unpack_from("<hh", frame, 8 + 24) == (2, 1)
    assert struct.unpack_from("<3d", frame, 8 + length) == (1530.5, 1535.25, 1540.125)


def test_decoder_splits_layouts_and_keeps_partial_frames():
    a = hyperion.encode_peak_frames(1, np.array([10.0, 10.001]), np.array([1, 2]),
                                    np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    b = hyperion.encode_peak_frame(1, 10.002, np.array([0, 2]), np.array([7.0, 8.0]))
    c = hyperion.encode_peak_frame(1, 10.003, np.array([1, 2]), np.array([9.0, 10.0, 11.0]))
    stream = a + b + c
    blocks, used = hyperion.decode_peak_frames(stream[:-5])
    assert used == len(a) + len(b)          # the cut frame stays for the next read
    assert [len(x.timestamp_s) for x in blocks] == [2, 1]
    np.testing.assert_array_equal(blocks[0].wavelengths_nm, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(blocks[0].peak_channel, [0, 1, 1])
    np.testing.assert_array_equal(blocks[1].peak_counts, [0, 2])
    np.testing.assert_allclose(blocks[0].timestamp_s, [10.0, 10.001], atol=1e-9)
    blocks, used = hyperion.decode_peak_frames(stream)
    assert used == len(stream) and blocks[-1].wavelengths_nm[0, 2] == 11.0


def test_corrupt_frame_is_an_error_not_a_crash():
    frame = bytearray(hyperion.encode_peak_frame(1, 1.0, np.array([3]), np.array([1.0, 2.0])))
    with pytest.raises(hyperion.HyperionError):
        hyperion.decode_peak_frames(bytes(frame))


def test_window_mapping_flags_missing_doubled_and_out_of_window():
    m = PeakMapper(np.array([1530.0, 1535.0, 1540.0]), window_nm=2.0)
    peaks = np.array([[1530.1, 1535.2, 1540.3, np.nan],
                      [1530.1, 1535.2, 1535.4, 1540.3],     # doubled S2
                      [1530.1, 1537.5, 1540.3, np.nan],     # S2 moved out of its window
                      [1530.1, 1540.3, np.nan, np.nan],     # S2 gone
                      [1532.5, 1540.3, np.nan, np.nan]])    # S2 gone, S1 moved out
    b = m.map(peaks, 0.0, np.arange(5.0))
    np.testing.assert_array_equal(b.peak_count[:, 1], [1, 2, 0, 0, 0])
    # a peak in the guard band that another sensor owns is not this grating moved
    np.testing.assert_array_equal(b.near_count[:, 1], [0, 0, 1, 0, 1])
    np.testing.assert_array_equal(b.peak_count[:, 2], 1)
    np.testing.assert_array_equal(b.near_count[:, 0], [0, 0, 0, 0, 1])
    assert np.isnan(b.wavelength_nm[1:, 1]).all() and b.wavelength_nm[0, 1] == 1535.2
    np.testing.assert_array_equal(b.wavelength_nm[:4, 0], 1530.1)
    assert np.isnan(b.wavelength_nm[4, 0]) and b.peak_count[4, 0] == 0


def test_fault_specifications():
    assert parse_fault("drop:S3@5") .kind == "drop"
    f = parse_fault("shift:S1@2:-4.5")
    assert (f.sensor, f.at_s, f.value) == ("S1", 2.0, -4.5)
    assert parse_fault("cut@4:1.5").value == 1.5
    with pytest.raises(InputError):
        parse_fault("melt:S1@3")


def test_client_talks_to_the_simulated_instrument():
    async def main():
        sim = SimulatedHyperion(_table(), SimConfig(rate_hz=2000, channels=2,
                                                    faults=[parse_fault("drop:S3@0.3")]))
        await sim.start()
        client = hyperion.HyperionClient("127.0.0.1", sim.command_port, sim.stream_port)
        try:
            assert await client.serial_number() == "SIM-HYPERION-0001"
            assert await client.channel_count() == 2
            assert await client.is_ready()
            with pytest.raises(hyperion.HyperionError):
                await client.command("#NoSuchCommand")
            await client.open_stream()
            mapper = PeakMapper(_table().wavelengths_nm[0], 2.5)
            batches = []
            loop = asyncio.get_running_loop()
            end = loop.time() + 0.6
            while loop.time() < end:
                batches.append(mapper.map_blocks(await client.read_blocks(1.0), 0.0))
            t = np.concatenate([b.time_s for b in batches])
            counts = np.concatenate([b.peak_count for b in batches])
            return sim, t, counts
        finally:
            await client.close()
            await sim.stop()

    sim, t, counts = asyncio.run(main())
    assert t.size > 600                                  # ~2 kHz for 0.6 s
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.median(np.diff(t)), 1 / 2000, rtol=1e-3)
    rel = t - sim._t0
    assert (counts[rel < 0.29, 2] == 1).all() and (counts[rel > 0.31, 2] == 0).all()
    assert (counts[:, [0, 1, 3]] == 1).all()


def test_simulator_rejects_unknown_sensor_in_fault():
    with pytest.raises(InputError):
        SimulatedHyperion(_table(), SimConfig(faults=[parse_fault("drop:S9@1")]))


def test_window_search_agrees_with_the_exhaustive_comparison():
    rng = np.random.default_rng(5)
    lam0 = 1520.0 + 5.0 * np.arange(12)
    m = PeakMapper(lam0, window_nm=2.0)
    peaks = lam0[rng.integers(0, 12, (400, 15))] + rng.uniform(-4.5, 4.5, (400, 15))
    peaks[rng.random(peaks.shape) < 0.1] = np.nan
    fast = m.map(peaks, 0.0, np.arange(400.0))
    S = lam0.size
    count, value, near = np.zeros(400 * S, np.int64), np.zeros(400 * S), np.zeros(400 * S, np.int64)
    m._map_group_overlapping(peaks, np.arange(S), count, value, near)
    np.testing.assert_array_equal(fast.peak_count, count.reshape(400, S))
    np.testing.assert_array_equal(fast.near_count, near.reshape(400, S))
    one = count.reshape(400, S) == 1
    np.testing.assert_array_equal(fast.wavelength_nm[one], value.reshape(400, S)[one])
    assert one.sum() > 1000 and (count > 1).any() and (near > 0).any()


def test_sensors_with_a_channel_only_see_their_fibre():
    # two fibres with gratings of the same nominal wavelengths
    m = PeakMapper(np.array([1530.0, 1535.0, 1530.0, 1535.0]), 2.5, channel=[1, 1, 2, 2])
    frames = hyperion.encode_peak_frames(1, np.array([1.0, 1.001]), np.array([2, 1]),
                                         np.array([[1530.1, 1535.1, 1530.3],
                                                   [1530.2, 1535.2, 1530.4]]))
    blocks, _ = hyperion.decode_peak_frames(frames)
    b = m.map_blocks(blocks, 0.0)
    np.testing.assert_array_equal(b.peak_count, [[1, 1, 1, 0], [1, 1, 1, 0]])
    np.testing.assert_allclose(b.wavelength_nm[:, 2], [1530.3, 1530.4])
    np.testing.assert_allclose(b.wavelength_nm[:, 0], [1530.1, 1530.2])


def test_injected_faults_reach_the_sensor_checks():
    from fbgcomp.runtime import health as H

    async def main():
        cfg = SimConfig(rate_hz=2000, channels=2, peaks_per_channel=6, noise_pm=0.2,
                        faults=[parse_fault("double:S2@0.2"), parse_fault("shift:S4@0.3:+3.5"),
                                parse_fault("stuck:S1@0.1")])
        sim = SimulatedHyperion(_table(), cfg)
        await sim.start()
        client = hyperion.HyperionClient("127.0.0.1", sim.command_port, sim.stream_port)
        try:
            await client.open_stream()
            mapper = PeakMapper(_table().wavelengths_nm[0], 2.5)
            checks = H.SensorChecks(4, H.HealthConfig(stuck_s=0.1))
            out, layouts = [], set()
            loop = asyncio.get_running_loop()
            end = loop.time() + 0.6
            while loop.time() < end:
                blocks = await client.read_blocks(1.0)
                layouts |= {tuple(b.peak_counts) for b in blocks}
                b = mapper.map_blocks(blocks, 0.0)
                status, _ = checks.check(b.time_s, b.wavelength_nm, b.peak_count, b.near_count)
                out.append((b.time_s - sim._t0, status))
            return np.concatenate([t for t, _ in out]), np.vstack([s for _, s in out]), layouts
        finally:
            await client.close()
            await sim.stop()

    t, status, layouts = asyncio.run(main())
    assert layouts == {(6, 6)}                           # padded to 6 peaks per channel
    late = t > 0.35
    assert (status[late, 1] == H.DOUBLED).all() and (status[t < 0.19, 1] == H.OK).all()
    assert (status[late, 3] == H.OUT_OF_WINDOW).all() and (status[t < 0.29, 3] == H.OK).all()
    assert (status[t > 0.25, 0] == H.STUCK).all() and (status[t < 0.09, 0] == H.OK).all()
    assert (status[:, 2] == H.OK).all()
