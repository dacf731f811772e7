"""Hyperion protocol codec, client and the simulated instrument, over real loopback sockets."""

import asyncio
import itertools
import struct

import numpy as np
import pytest

from fbgcomp.errors import InputError
from fbgcomp.runtime import hyperion
from fbgcomp.runtime.simulator import SignalTable, SimConfig, SimulatedHyperion, parse_fault
from fbgcomp.runtime.windows import PeakMapper
from test_runtime_support import free_port


def _table():
    t = np.arange(0.0, 60.0, 0.5)
    wl = 1530.0 + 5.0 * np.arange(4)[None, :] + 0.01 * np.sin(t[:, None] / 7 + np.arange(4))
    return SignalTable(t, wl, ["S1", "S2", "S3", "S4"])


def test_peak_frame_layout_matches_the_protocol_byte_for_byte():
    frame = hyperion.encode_peak_frame(
        42, 1700000000.25, np.array([2, 1]), np.array([1530.5, 1535.25, 1540.125])
    )
    status, rtype, msg_len, content_len = struct.unpack_from("<BBHI", frame, 0)
    assert (status, rtype, msg_len) == (0, 0, 0) and content_len == len(frame) - 8
    length, _version, _, serial, t_int, t_frac = struct.unpack_from("<HHIQII", frame, 8)
    assert length == 24 + 2 * 2 and serial == 42
    assert t_int == 1700000000 and t_frac == 250_000_000
    assert struct.unpack_from("<hh", frame, 8 + 24) == (2, 1)
    assert struct.unpack_from("<3d", frame, 8 + length) == (1530.5, 1535.25, 1540.125)


def test_decoder_splits_layouts_and_keeps_partial_frames():
    a = hyperion.encode_peak_frames(
        1, np.array([10.0, 10.001]), np.array([1, 2]), np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    )
    b = hyperion.encode_peak_frame(1, 10.002, np.array([0, 2]), np.array([7.0, 8.0]))
    c = hyperion.encode_peak_frame(1, 10.003, np.array([1, 2]), np.array([9.0, 10.0, 11.0]))
    stream = a + b + c
    blocks, used = hyperion.decode_peak_frames(stream[:-5])
    assert used == len(a) + len(b)  # the cut frame stays for the next read
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
    peaks = np.array(
        [
            [1530.1, 1535.2, 1540.3, np.nan],
            [1530.1, 1535.2, 1535.4, 1540.3],  # doubled S2
            [1530.1, 1537.5, 1540.3, np.nan],  # S2 moved out of its window
            [1530.1, 1540.3, np.nan, np.nan],  # S2 gone
            [1532.5, 1540.3, np.nan, np.nan],
        ]
    )  # S2 gone, S1 moved out
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
    assert parse_fault("drop:S3@5").kind == "drop"
    f = parse_fault("shift:S1@2:-4.5")
    assert (f.sensor, f.at_s, f.value) == ("S1", 2.0, -4.5)
    assert parse_fault("cut@4:1.5").value == 1.5
    with pytest.raises(InputError):
        parse_fault("melt:S1@3")
    f = parse_fault("shift:S2@3:+2/10")  # a mode hop there and back
    assert (f.value, f.at_s, f.until_s) == (2.0, 3.0, 13.0) and not f.active(13.0)
    assert parse_fault("drop:S3@5").until_s == float("inf")
    assert (parse_fault("garbage@6").kind, parse_fault("garbage@6:100").value) == ("garbage", 100.0)
    for bad in ("drop:S3@5/0", "drop:S3@5/-1", "garbage@1:1e9", "cut@-1:2", "shift:S1@2:nan"):
        with pytest.raises(InputError):
            parse_fault(bad)


def test_temporary_faults_end_and_garbage_makes_the_source_reconnect():
    """A drop with a duration brings the grating back; a garbage burst is refused by the
    client's decoder and the source reconnects to the same instrument."""
    from fbgcomp.runtime.sources import HyperionSource

    async def main():
        sim = SimulatedHyperion(
            _table(),
            SimConfig(rate_hz=2000, faults=[parse_fault("drop:S3@0.2/0.2"), parse_fault("garbage@0.6:2000")]),
        )
        await sim.start()
        mapper = PeakMapper(_table().wavelengths_nm[0], 2.5)
        src = HyperionSource(
            "127.0.0.1",
            sim.stream_port,
            sim.command_port,
            mapper,
            backoff_initial_s=0.05,
            stall_timeout_s=5.0,
        )
        batches = []
        try:
            agen = src.batches()
            loop = asyncio.get_running_loop()
            end = loop.time() + 10.0
            while loop.time() < end:
                b = await asyncio.wait_for(agen.__anext__(), 5.0)
                if b is not None and len(b):
                    batches.append(b)
                    if src.reconnects and b.time_s[-1] - sim._t0 > 1.0:
                        break
            await agen.aclose()
            return sim, batches, src.reconnects
        finally:
            await src.close()
            await sim.stop()

    sim, batches, reconnects = asyncio.run(main())
    t = np.concatenate([b.time_s for b in batches]) - sim._t0
    counts = np.concatenate([b.peak_count for b in batches])
    assert (counts[(t > 0.21) & (t < 0.39), 2] == 0).all()
    assert (counts[(t < 0.19) | ((t > 0.41) & (t < 0.59)), 2] == 1).all()
    assert sim.garbage_sent == 1 and reconnects >= 1
    assert (t > 1.0).any() and (counts[t > 0.61] == 1).all()


def test_client_talks_to_the_simulated_instrument():
    async def main():
        sim = SimulatedHyperion(
            _table(), SimConfig(rate_hz=2000, channels=2, faults=[parse_fault("drop:S3@0.3")])
        )
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
    assert t.size > 600  # ~2 kHz for 0.6 s
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.median(np.diff(t)), 1 / 2000, rtol=1e-3)
    rel = t - sim._t0
    assert (counts[rel < 0.29, 2] == 1).all() and (counts[rel > 0.31, 2] == 0).all()
    assert (counts[:, [0, 1, 3]] == 1).all()


def test_simulator_rejects_unknown_sensor_in_fault():
    with pytest.raises(InputError):
        SimulatedHyperion(_table(), SimConfig(faults=[parse_fault("drop:S9@1")]))


@pytest.mark.parametrize("n", [400, 1])
def test_window_search_agrees_with_the_exhaustive_comparison(n):
    # NaN and infinite peaks, doubled windows and peaks in the guard bands, in a batch and in
    # the one-frame batch of a high frame rate
    rng = np.random.default_rng(5)
    lam0 = 1520.0 + 5.0 * np.arange(12)
    m = PeakMapper(lam0, window_nm=2.0)
    frames = [(400, 15), (2000, 6)][n == 1]
    peaks_all = lam0[rng.integers(0, 12, frames)] + rng.uniform(-4.5, 4.5, frames)
    r = rng.random(peaks_all.shape)
    peaks_all[r < 0.1] = np.nan
    peaks_all[(r >= 0.1) & (r < 0.12)] = np.inf
    peaks_all[(r >= 0.12) & (r < 0.14)] = -np.inf
    S = lam0.size
    seen = np.zeros(3, int)
    for peaks in np.split(peaks_all, peaks_all.shape[0] // n):
        fast = m.map(peaks, 0.0, np.arange(float(n)))
        count, value, near = np.zeros(n * S, np.int64), np.zeros(n * S), np.zeros(n * S, np.int64)
        m._map_group_overlapping(peaks, np.arange(S), count, value, near)
        np.testing.assert_array_equal(fast.peak_count, count.reshape(n, S))
        np.testing.assert_array_equal(fast.near_count, near.reshape(n, S))
        one = count.reshape(n, S) == 1
        np.testing.assert_array_equal(fast.wavelength_nm[one], value.reshape(n, S)[one])
        assert np.isnan(fast.wavelength_nm[~one]).all()
        seen += [one.sum(), (count > 1).sum(), (near > 0).sum()]
    assert seen[0] > 1000 and seen[1] > 0 and seen[2] > 0


def test_sensors_with_a_channel_only_see_their_fibre():
    # two fibres with gratings of the same nominal wavelengths
    m = PeakMapper(np.array([1530.0, 1535.0, 1530.0, 1535.0]), 2.5, channel=[1, 1, 2, 2])
    frames = hyperion.encode_peak_frames(
        1,
        np.array([1.0, 1.001]),
        np.array([2, 1]),
        np.array([[1530.1, 1535.1, 1530.3], [1530.2, 1535.2, 1530.4]]),
    )
    blocks, _ = hyperion.decode_peak_frames(frames)
    b = m.map_blocks(blocks, 0.0)
    np.testing.assert_array_equal(b.peak_count, [[1, 1, 1, 0], [1, 1, 1, 0]])
    np.testing.assert_allclose(b.wavelength_nm[:, 2], [1530.3, 1530.4])
    np.testing.assert_allclose(b.wavelength_nm[:, 0], [1530.1, 1530.2])


def test_injected_faults_reach_the_sensor_checks():
    from fbgcomp.runtime import health as H

    async def main():
        cfg = SimConfig(
            rate_hz=2000,
            channels=2,
            peaks_per_channel=6,
            noise_pm=0.2,
            faults=[
                parse_fault("double:S2@0.2"),
                parse_fault("shift:S4@0.3:+3.5"),
                parse_fault("stuck:S1@0.1"),
            ],
        )
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
    assert layouts == {(6, 6)}  # padded to 6 peaks per channel
    late = t > 0.35
    assert (status[late, 1] == H.DOUBLED).all() and (status[t < 0.19, 1] == H.OK).all()
    assert (status[late, 3] == H.OUT_OF_WINDOW).all() and (status[t < 0.29, 3] == H.OK).all()
    assert (status[t > 0.25, 0] == H.STUCK).all() and (status[t < 0.09, 0] == H.OK).all()
    assert (status[:, 2] == H.OK).all()


# --------------------------------------------------------------------------- hostile streams
# Issue 13, finding 3: random bytes or a header announcing a 4 GiB frame made the decoder wait
# for the rest forever (no error, no reconnect, the buffer growing with every read).


class _FakeStream:
    """A stream port on loopback whose n-th connection is served by ``scripts[n]`` (the last
    one repeats); each script is ``async def script(writer)``."""

    def __init__(self, *scripts):
        self.scripts = scripts
        self.connections = 0
        self.server = None

    async def start(self) -> int:
        async def serve(reader, writer):
            script = self.scripts[min(self.connections, len(self.scripts) - 1)]
            self.connections += 1
            try:
                await script(writer)
            except (ConnectionError, OSError):
                pass
            finally:
                writer.close()

        self.server = await asyncio.start_server(serve, "127.0.0.1", 0)
        return self.server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        self.server.close()


def _endless(chunk: bytes, first: bytes = b"", cap_bytes: int = 32 << 20):
    """Send ``first`` then ``chunk`` again and again as fast as the reader takes it (up to
    ``cap_bytes``, so a decoder that buffers everything is caught without exhausting the
    machine), then hold the connection open."""

    async def script(writer):
        writer.write(first)
        sent = len(first)
        while sent < cap_bytes:
            writer.write(chunk)
            sent += len(chunk)
            await writer.drain()
        await asyncio.sleep(30)

    return script


def _valid_frames(writer_t0=1700000000.0, n=2000, rate_hz=2000.0):
    lam = np.array([1530.0, 1535.0, 1540.0, 1545.0])

    async def script(writer):
        for i in range(0, n, 20):
            t = writer_t0 + np.arange(i, i + 20) / rate_hz
            writer.write(hyperion.encode_peak_frames(7, t, np.array([2, 2]), np.tile(lam, (t.size, 1))))
            await writer.drain()
            await asyncio.sleep(0.01)
        await asyncio.sleep(30)

    return script


def _garbage(seed=13, size=1 << 16) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def _huge_header() -> bytes:
    """Outer header of a peak frame announcing 4 GiB of content, and a plausible peak header."""
    return hyperion.HEADER.pack(0, 0, 0, 0xFFFFFFFF) + hyperion.PEAK_HEADER.pack(
        24 + 2 * 2, 1, 0, 1, 1700000000, 0
    )


def test_a_4_gib_frame_header_is_rejected_at_once():
    async def main():
        fake = _FakeStream(_endless(b"", first=_huge_header(), cap_bytes=0))
        port = await fake.start()
        client = hyperion.HyperionClient("127.0.0.1", stream_port=port)
        try:
            await client.open_stream()
            t0 = asyncio.get_running_loop().time()
            with pytest.raises(hyperion.HyperionError, match="corrupt"):
                await client.read_blocks(5.0)
            return asyncio.get_running_loop().time() - t0
        finally:
            await client.close()
            await fake.stop()

    # before: the 4 GiB were awaited until the stall timeout, and the link was kept
    assert asyncio.run(main()) < 1.0


def test_random_bytes_drop_the_link_and_the_source_reconnects(caplog):
    from fbgcomp.runtime.sources import HyperionSource

    async def main():
        fake = _FakeStream(_endless(_garbage()), _valid_frames())
        port = await fake.start()
        mapper = PeakMapper(np.array([1530.0, 1535.0, 1540.0, 1545.0]), 2.0)
        # the command port refuses: the source streams without it
        src = HyperionSource(
            "127.0.0.1", port, free_port(), mapper, backoff_initial_s=0.05, stall_timeout_s=5.0
        )
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            agen = src.batches()
            batch = await asyncio.wait_for(agen.__anext__(), 10.0)
            elapsed = loop.time() - t0
            await agen.aclose()
            return batch, elapsed, src.reconnects, fake.connections
        finally:
            await src.close()
            await fake.stop()

    with caplog.at_level("WARNING", logger="fbgcomp.runtime"):
        batch, elapsed, reconnects, connections = asyncio.run(main())
    # the garbage is refused as corrupt on the first read, not by the 5 s stall timeout
    assert elapsed < 5.0
    assert reconnects == 1 and connections == 2
    assert any("corrupt" in r.getMessage() for r in caplog.records)
    assert (batch.peak_count == 1).all() and len(batch) > 0


@pytest.mark.parametrize(
    "first, chunk",
    [(b"", _garbage(seed=3)), (_huge_header(), bytes(1 << 16))],
    ids=["random-bytes", "4GiB-header-then-zeros"],
)
def test_memory_stays_bounded_while_a_stream_sends_garbage(first, chunk):
    """Read a hostile stream for 0.5 s, reconnecting after every error, as the source does:
    the Python heap (the receive buffer above all) must not grow with the bytes received."""
    import tracemalloc

    async def main():
        fake = _FakeStream(_endless(chunk, first=first))
        port = await fake.start()
        client = hyperion.HyperionClient("127.0.0.1", stream_port=port)
        loop = asyncio.get_running_loop()
        errors = 0
        end = loop.time() + 0.5
        try:
            while loop.time() < end:
                await client.open_stream()
                try:
                    await asyncio.wait_for(client.read_blocks(5.0), end - loop.time())
                except hyperion.HyperionError:
                    errors += 1
                except TimeoutError:
                    break
                finally:
                    await client.close()
            return errors
        finally:
            await fake.stop()

    tracemalloc.start()
    try:
        errors = asyncio.run(main())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, f"{peak / 2**20:.0f} MiB"  # before: all the stream sent was kept
    assert errors >= 1


@pytest.mark.parametrize(
    "first, chunk",
    [(b"", _garbage(seed=3)), (_huge_header(), bytes(1 << 16))],
    ids=["random-bytes", "4GiB-header-then-zeros"],
)
def test_a_closed_connection_is_freed_without_the_cyclic_collector(first, chunk):
    """With the cyclic garbage collector off, every connection refused as corrupt and closed
    is freed by reference counting alone: its StreamReader (and the receive buffer it holds)
    is gone right after close(), and the heap does not grow by a buffer per connection.
    Before: the reader's frame sat in the error's traceback, which asyncio keeps in a reference
    cycle, so each connection kept ~350-500 KiB until gc ran (what made the test above flaky)."""
    import gc
    import tracemalloc
    import weakref

    async def main():
        fake = _FakeStream(_endless(chunk, first=first))
        port = await fake.start()
        client = hyperion.HyperionClient("127.0.0.1", stream_port=port)
        loop = asyncio.get_running_loop()
        alive, buffered, grown = [], [], []
        try:
            await client.open_stream()  # warm-up: first-use allocations of asyncio
            await client.close()
            base = tracemalloc.get_traced_memory()[0]
            for _ in range(5):
                await client.open_stream()
                reader = weakref.ref(client._stream[0])
                # let the sender fill the reader's buffer before the first read
                end = loop.time() + 2.0
                while len(reader()._buffer) < 2 * hyperion.READ_SIZE and loop.time() < end:
                    await asyncio.sleep(0.01)
                buffered.append(len(reader()._buffer))
                with pytest.raises(hyperion.HyperionError, match="corrupt"):
                    await asyncio.wait_for(client.read_blocks(5.0), 5.0)
                await client.close()
                alive.append(reader() is not None)
                grown.append(tracemalloc.get_traced_memory()[0] - base)
            return alive, buffered, grown
        finally:
            await client.close()
            await fake.stop()

    gc.collect()
    gc.disable()
    tracemalloc.start()
    try:
        alive, buffered, grown = asyncio.run(main())
    finally:
        tracemalloc.stop()
        gc.enable()
    assert min(buffered) >= 2 * hyperion.READ_SIZE  # there was a buffer worth freeing
    assert alive == [False] * 5, "a closed connection's reader still referenced"
    # measured: ~10 KiB a connection left to the collector (the exception and its frames),
    # ~350-500 KiB before the fix
    assert grown[-1] < 5 * 48 << 10, [g >> 10 for g in grown]


# --------------------------------------------------------------------------- decoder properties
from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SMALL = hyperion.FrameLimits(channels=4, peaks_per_channel=8)  # frames of at most 296 bytes


@st.composite
def _frame(draw, limits=SMALL):
    """(bytes, serial, t, counts, peaks) of one valid frame within ``limits``."""
    n_ch = draw(st.integers(0, limits.channels))
    counts = np.array(
        draw(st.lists(st.integers(0, limits.peaks_per_channel), min_size=n_ch, max_size=n_ch)), dtype=np.int16
    )
    peaks = np.array(
        draw(st.lists(st.floats(1400.0, 1700.0), min_size=int(counts.sum()), max_size=int(counts.sum()))),
        dtype=np.float64,
    )
    serial = draw(st.integers(0, 2**64 - 1))
    t = draw(st.integers(0, 2**32 - 2)) + draw(st.integers(0, 999_999)) * 1e-6
    return hyperion.encode_peak_frame(serial, t, counts, peaks), serial, t, counts, peaks


def _error_frame(draw):
    return hyperion.encode_response(
        draw(st.binary(max_size=40)), draw(st.binary(max_size=40)), status=draw(st.integers(1, 255))
    )


@st.composite
def _hostile_stream(draw):
    """Valid frames, instrument error frames, random bytes and valid frames with bytes
    overwritten, in any order."""
    parts = []
    for kind in draw(st.lists(st.sampled_from(["frame", "error", "random", "mutated"]), max_size=8)):
        if kind == "frame":
            parts.append(draw(_frame())[0])
        elif kind == "error":
            parts.append(_error_frame(draw))
        elif kind == "random":
            parts.append(draw(st.binary(min_size=1, max_size=300)))
        else:
            frame = bytearray(draw(_frame())[0])
            for _ in range(draw(st.integers(1, 4))):
                frame[draw(st.integers(0, len(frame) - 1))] = draw(st.integers(0, 255))
            parts.append(bytes(frame))
    return b"".join(parts)


def _chunks(data: bytes, cuts: list[int]) -> list[bytes]:
    edges = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    return [data[a:b] for a, b in itertools.pairwise(edges)]


def _check_block(block: hyperion.PeakBlock, limits: hyperion.FrameLimits) -> None:
    n = block.timestamp_s.size
    assert block.serial_number.shape == (n,) and n >= 1
    assert block.peak_counts.size <= limits.channels
    assert ((block.peak_counts >= 0) & (block.peak_counts <= limits.peaks_per_channel)).all()
    assert block.wavelengths_nm.shape == (n, int(block.peak_counts.sum()))
    assert block.peak_channel.size == block.wavelengths_nm.shape[1]


@settings(max_examples=400, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(
    data=st.one_of(st.binary(max_size=2000), _hostile_stream()),
    cuts=st.lists(st.integers(0, 4000), max_size=6),
)
def test_any_bytes_decode_to_valid_frames_or_a_corrupt_error(data, cuts):
    """Whatever arrives, in whatever pieces: each piece yields valid frames or raises the
    decoder's corrupt-stream error (after which the link is dropped), never anything else;
    and between pieces less than one maximum frame is kept."""
    decoder = hyperion.PeakStreamDecoder(SMALL)
    for piece in _chunks(data, cuts):
        try:
            blocks = decoder.feed(piece)
        except hyperion.HyperionError as exc:
            event("refused as corrupt")
            assert "corrupt" in str(exc)
            assert decoder.buffered == 0
            return
        for b in blocks:
            event("valid frames decoded")
            _check_block(b, SMALL)
        assert decoder.buffered < SMALL.max_frame_bytes


@settings(max_examples=200, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(
    frames=st.lists(_frame(), min_size=1, max_size=12),
    errors=st.lists(st.booleans(), max_size=12),
    cuts=st.lists(st.integers(0, 5000), max_size=8),
    data=st.data(),
)
def test_valid_frames_decode_exactly_in_any_pieces(frames, errors, cuts, data):
    """Valid frames (and the instrument's error frames between them, which are skipped) come
    out exactly as sent, however the stream is cut into reads."""
    stream = b""
    for i, f in enumerate(frames):
        if i < len(errors) and errors[i]:
            stream += _error_frame(data.draw)
        stream += f[0]
    decoder = hyperion.PeakStreamDecoder(SMALL)
    got = []
    for piece in _chunks(stream, cuts):
        for b in decoder.feed(piece):
            _check_block(b, SMALL)
            for k in range(b.timestamp_s.size):
                got.append(
                    (
                        int(b.serial_number[k]),
                        b.timestamp_s[k],
                        b.peak_counts.tolist(),
                        b.wavelengths_nm[k].tolist(),
                    )
                )
        assert decoder.buffered < SMALL.max_frame_bytes
    assert decoder.buffered == 0
    assert [(s, c.tolist(), p.tolist()) for _, s, _, c, p in frames] == [(s, c, p) for s, _, c, p in got]
    np.testing.assert_allclose([t for _, _, t, _, _ in frames], [t for _, t, _, _ in got], rtol=0, atol=2e-6)


@given(
    content_len=st.integers(SMALL.max_frame_bytes - hyperion.HEADER_SIZE + 1, 2**32 - 1),
    status=st.integers(0, 255),
)
def test_an_oversized_header_is_refused_from_its_first_8_bytes(content_len, status):
    """The frame length is checked before any of the frame is awaited (peak or error frame)."""
    with pytest.raises(hyperion.HyperionError, match="corrupt"):
        hyperion.decode_peak_frames(hyperion.HEADER.pack(status, 0, 0, content_len), SMALL)


def test_the_largest_frame_the_limits_allow_is_decoded():
    limits = hyperion.FrameLimits(channels=3, peaks_per_channel=5)
    counts = np.array([5, 5, 5])
    frame = hyperion.encode_peak_frame(1, 2.5, counts, 1500.0 + np.arange(15.0))
    assert len(frame) == limits.max_frame_bytes == 8 + 24 + 2 * 3 + 8 * 3 * 5
    blocks, used = hyperion.decode_peak_frames(frame, limits)
    assert used == len(frame) and blocks[0].wavelengths_nm.shape == (1, 15)
    with pytest.raises(hyperion.HyperionError):  # one more peak on a channel: refused
        hyperion.decode_peak_frames(
            hyperion.encode_peak_frame(1, 2.5, np.array([6, 4, 5]), 1500.0 + np.arange(15.0)), limits
        )
    with pytest.raises(hyperion.HyperionError):  # a fourth channel: refused
        hyperion.decode_peak_frames(
            hyperion.encode_peak_frame(1, 2.5, np.array([1, 1, 1, 1]), 1500.0 + np.arange(4.0)), limits
        )


def test_a_command_answer_announcing_4_gib_is_refused_before_it_is_read():
    async def main():
        async def answer(reader, writer):
            await hyperion.read_request(reader)
            writer.write(hyperion.HEADER.pack(0, 0, 0, 0xFFFFFFFF) + bytes(1000))
            await writer.drain()
            await asyncio.sleep(30)

        server = await asyncio.start_server(answer, "127.0.0.1", 0)
        client = hyperion.HyperionClient("127.0.0.1", server.sockets[0].getsockname()[1], timeout_s=5.0)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            with pytest.raises(hyperion.HyperionError, match="corrupt"):
                await client.serial_number()
            return loop.time() - t0
        finally:
            await client.close()
            server.close()

    assert asyncio.run(main()) < 1.0  # before: waited the 5 s timeout for the 4 GiB
