"""Luna / Micron Optics Hyperion TCP protocol: codec and asyncio client.

Two TCP ports are used by an instrument:

* command port (51971): a request is the 8-byte header ``'BBHI'`` = (request_options, 0,
  len(command), len(argument)) followed by the ASCII command (``#GetSerialNumber``) and the
  ASCII argument; the response is the 8-byte header ``'BBHI'`` = (status, response_type,
  message_length, content_length) followed by the message and the content.
* peak streaming port (51972): every frame is the 8-byte response header, then a content of
  ``content_length`` bytes = 24-byte peak header ``'HHIQII'`` (length, version, reserved,
  serial_number, timestamp_int_s, timestamp_frac_ns), int16 peak counts per channel up to byte
  ``length``, then float64 peak wavelengths in nm, channel by channel.

Everything is little-endian (the instrument's native order). Frames are decoded in vectorised
batches: consecutive frames with the same layout (same peak counts) are viewed as one numpy
record array, so decoding cost per frame is a few hundred nanoseconds.

A stream is only trusted as far as its layout allows (:class:`FrameLimits`). With ``C`` channels
and at most ``P`` peaks per channel the largest frame the protocol can carry is

    8 (response header) + 24 (peak header) + 2 C (int16 counts) + 8 C P (float64 peaks) bytes,

65 600 bytes for the defaults (16 channels, 512 peaks per channel; the channel count is taken
from the instrument's ``#GetDutChannelCount`` when its command port answers). Every header is
checked as soon as its bytes arrive: a frame announced longer than that, a peak header whose
``length`` does not fit the channels, counts outside ``0..P`` or that disagree with the
content length raise :class:`HyperionError` ("corrupt peak stream") at once, so garbage on the
port drops the link within one frame and the receive buffer never holds more than one
maximum frame plus one read.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import struct
import traceback
from dataclasses import dataclass

import numpy as np

COMMAND_PORT = 51971
STREAM_PORT = 51972

HEADER = struct.Struct("<BBHI")  # 8 bytes, request and response
PEAK_HEADER = struct.Struct("<HHIQII")  # 24 bytes
HEADER_SIZE = HEADER.size
PEAK_HEADER_SIZE = PEAK_HEADER.size
PEAK_HEADER_VERSION = 1

DEFAULT_CHANNELS = 16  # when the instrument does not say (no command port)
MAX_CHANNELS = 128  # the most a reported channel count is believed
# An interrogator sweeps at most ~160 nm and cannot separate peaks closer than ~0.3 nm: a
# channel never carries 512 peaks. Our bound, not a vendor figure.
MAX_PEAKS_PER_CHANNEL = 512
READ_SIZE = 1 << 16  # bytes asked of the socket per read
MAX_RESPONSE_BYTES = 1 << 20  # command-port answer content (serial number, counts: bytes)


class HyperionError(Exception):
    """The instrument answered a command with a non-zero status, or the stream is corrupt."""


@dataclass(frozen=True)
class FrameLimits:
    """The largest peak frame a stream may announce: ``channels`` × ``peaks_per_channel``."""

    channels: int = DEFAULT_CHANNELS
    peaks_per_channel: int = MAX_PEAKS_PER_CHANNEL

    @property
    def max_frame_bytes(self) -> int:
        """8 + 24 + 2 C + 8 C P bytes: headers, int16 counts and float64 peaks."""
        c, p = self.channels, self.peaks_per_channel
        return HEADER_SIZE + PEAK_HEADER_SIZE + 2 * c + 8 * c * p


DEFAULT_LIMITS = FrameLimits()


# --------------------------------------------------------------------------- command port
def encode_request(command: str, argument: str | bytes = b"", request_options: int = 0) -> bytes:
    """Bytes of one command-port request."""
    cmd = command.encode("ascii")
    arg = argument.encode("ascii") if isinstance(argument, str) else bytes(argument)
    return HEADER.pack(request_options, 0, len(cmd), len(arg)) + cmd + arg


def encode_response(
    message: str | bytes = b"", content: bytes = b"", status: int = 0, response_type: int = 0
) -> bytes:
    """Bytes of one command-port response (also the outer header of a stream frame)."""
    msg = message.encode("ascii") if isinstance(message, str) else bytes(message)
    return HEADER.pack(status, response_type, len(msg), len(content)) + msg + content


async def read_request(reader: asyncio.StreamReader) -> tuple[int, str, bytes]:
    """Read one request: (request_options, command, argument). Raises IncompleteReadError at EOF."""
    options, _, cmd_len, arg_len = HEADER.unpack(await reader.readexactly(HEADER_SIZE))
    cmd = (await reader.readexactly(cmd_len)).decode("ascii", "replace")
    arg = await reader.readexactly(arg_len) if arg_len else b""
    return options, cmd, arg


async def read_response(
    reader: asyncio.StreamReader, max_content_bytes: int = MAX_RESPONSE_BYTES
) -> tuple[int, int, bytes, bytes]:
    """Read one response: (status, response_type, message, content).

    A content longer than ``max_content_bytes`` raises HyperionError before it is read: the
    answers this client asks for are a few bytes, and a bogus length must not be buffered.
    """
    status, rtype, msg_len, content_len = HEADER.unpack(await reader.readexactly(HEADER_SIZE))
    if content_len > max_content_bytes:
        raise HyperionError(
            f"corrupt response: {content_len} bytes of content announced, more than {max_content_bytes}"
        )
    message = await reader.readexactly(msg_len) if msg_len else b""
    content = await reader.readexactly(content_len) if content_len else b""
    return status, rtype, message, content


# --------------------------------------------------------------------------- peak stream
def encode_peak_frame(
    serial_number: int, timestamp_s: float, peak_counts: np.ndarray, wavelengths_nm: np.ndarray
) -> bytes:
    """Bytes of one streamed peak frame (outer header + peak header + counts + peaks).

    ``peak_counts`` holds one int16 count per channel, ``wavelengths_nm`` the concatenated
    peaks of all channels in channel order (``sum(peak_counts)`` values).
    """
    counts = np.asarray(peak_counts, dtype="<i2")
    peaks = np.asarray(wavelengths_nm, dtype="<f8")
    length = PEAK_HEADER_SIZE + counts.nbytes
    t_int = int(timestamp_s)
    t_frac_ns = round((timestamp_s - t_int) * 1e9)
    if t_frac_ns >= 1_000_000_000:
        t_int, t_frac_ns = t_int + 1, t_frac_ns - 1_000_000_000
    content = (
        PEAK_HEADER.pack(length, PEAK_HEADER_VERSION, 0, serial_number, t_int, t_frac_ns)
        + counts.tobytes()
        + peaks.tobytes()
    )
    return HEADER.pack(0, 0, 0, len(content)) + content


def encode_peak_frames(
    serial_number: int, timestamps_s: np.ndarray, peak_counts: np.ndarray, wavelengths_nm: np.ndarray
) -> bytes:
    """Vectorised encoding of ``n`` frames that share one layout.

    ``peak_counts`` (C,) is common to all frames; ``wavelengths_nm`` is (n, sum(peak_counts)).
    """
    counts = np.asarray(peak_counts, dtype="<i2")
    peaks = np.ascontiguousarray(wavelengths_nm, dtype="<f8")
    n = peaks.shape[0]
    length = PEAK_HEADER_SIZE + counts.nbytes
    content_len = length + peaks.shape[1] * 8
    dtype = _frame_dtype(counts.size, peaks.shape[1])
    rec = np.zeros(n, dtype=dtype)
    rec["content_length"] = content_len
    rec["length"] = length
    rec["version"] = PEAK_HEADER_VERSION
    rec["serial"] = serial_number
    ts = np.asarray(timestamps_s, dtype=np.float64)
    t_int = np.floor(ts)
    rec["t_int"] = t_int.astype(np.uint32)
    rec["t_frac"] = np.minimum(np.round((ts - t_int) * 1e9), 999_999_999).astype(np.uint32)
    if counts.size:
        rec["counts"] = counts
    if peaks.shape[1]:
        rec["peaks"] = peaks
    return rec.tobytes()


@functools.lru_cache(maxsize=64)
def _frame_dtype(n_channels: int, n_peaks: int) -> np.dtype:
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [
        ("status", "u1"),
        ("rtype", "u1"),
        ("msg_len", "<u2"),
        ("content_length", "<u4"),
        ("length", "<u2"),
        ("version", "<u2"),
        ("reserved", "<u4"),
        ("serial", "<u8"),
        ("t_int", "<u4"),
        ("t_frac", "<u4"),
    ]
    if n_channels:
        fields.append(("counts", "<i2", (n_channels,)))
    if n_peaks:
        fields.append(("peaks", "<f8", (n_peaks,)))
    return np.dtype(fields)


@functools.lru_cache(maxsize=64)
def _counts(raw: bytes, n_peaks: int, peaks_per_channel: int) -> np.ndarray:
    """The per-channel peak counts of a layout (int16, read-only), checked once per layout: a
    stream repeats one layout frame after frame, so the checks cost nothing per frame."""
    counts = np.frombuffer(raw, dtype="<i2").astype(np.int16)
    if (counts < 0).any() or (counts > peaks_per_channel).any() or int(counts.sum()) != n_peaks:
        raise HyperionError(
            f"corrupt peak stream: counts sum {int(counts.sum())} != {n_peaks} "
            f"peaks, or a count outside 0..{peaks_per_channel}"
        )
    counts.setflags(write=False)
    return counts


@functools.lru_cache(maxsize=64)
def _peak_channel(counts_raw: bytes) -> np.ndarray:
    counts = np.frombuffer(counts_raw, dtype=np.int16)
    out = np.repeat(np.arange(counts.size), np.maximum(counts, 0))
    out.setflags(write=False)
    return out


@dataclass
class PeakBlock:
    """Frames of one layout decoded together.

    Attributes
    ----------
    timestamp_s : (n,) float64 instrument time stamps (s since the epoch)
    serial_number : (n,) uint64
    peak_counts : (C,) int16 peak count per channel, common to all n frames
    wavelengths_nm : (n, sum(peak_counts)) float64, channel by channel
    """

    timestamp_s: np.ndarray
    serial_number: np.ndarray
    peak_counts: np.ndarray
    wavelengths_nm: np.ndarray

    @property
    def peak_channel(self) -> np.ndarray:
        """Channel index (0-based) of every peak column (read-only; one array per layout)."""
        return _peak_channel(self.peak_counts.tobytes())


def decode_peak_frames(
    buffer: bytes | bytearray | memoryview, limits: FrameLimits = DEFAULT_LIMITS
) -> tuple[list[PeakBlock], int]:
    """Decode every complete frame in ``buffer``.

    Returns the decoded blocks (runs of frames with identical layout) and the number of bytes
    consumed; the caller keeps the remaining bytes for the next read. Those are always less
    than ``limits.max_frame_bytes``: a header that does not fit ``limits`` raises
    :class:`HyperionError` as soon as its bytes are in ``buffer``, without waiting for the
    frame it announces.
    """
    buf = memoryview(buffer).cast("B")
    total = len(buf)
    max_frame = limits.max_frame_bytes
    max_length = PEAK_HEADER_SIZE + 2 * limits.channels
    pos = 0
    blocks: list[PeakBlock] = []
    while total - pos >= HEADER_SIZE:
        status, _, msg_len, content_len = HEADER.unpack_from(buf, pos)
        frame_len = HEADER_SIZE + msg_len + content_len
        if frame_len > max_frame:
            raise HyperionError(
                f"corrupt peak stream: a frame of {frame_len} bytes announced, more than the "
                f"{max_frame} bytes of {limits.channels} channels x "
                f"{limits.peaks_per_channel} peaks"
            )
        if status != 0 or msg_len != 0:
            # Not a peak frame (an error message from the instrument): skip it whole.
            if total - pos < frame_len:
                break
            pos += frame_len
            continue
        if content_len < PEAK_HEADER_SIZE:
            raise HyperionError(
                f"corrupt peak stream: content of {content_len} bytes, shorter "
                f"than the {PEAK_HEADER_SIZE}-byte peak header"
            )
        if total - pos < HEADER_SIZE + PEAK_HEADER_SIZE:
            break
        length, _, _, serial, t_int, t_frac = PEAK_HEADER.unpack_from(buf, pos + HEADER_SIZE)
        if (
            length < PEAK_HEADER_SIZE
            or length > min(content_len, max_length)
            or (length - PEAK_HEADER_SIZE) % 2
            or (content_len - length) % 8
        ):
            raise HyperionError(f"corrupt peak stream: peak header length={length}, content={content_len}")
        n_ch = (length - PEAK_HEADER_SIZE) // 2
        n_pk = (content_len - length) // 8
        if total - pos < HEADER_SIZE + length:
            break
        counts = _counts(
            bytes(buf[pos + HEADER_SIZE + PEAK_HEADER_SIZE : pos + HEADER_SIZE + length]),
            n_pk,
            limits.peaks_per_channel,
        )
        if total - pos < frame_len:
            break
        n_max = (total - pos) // frame_len
        if n_max == 1:  # one frame (a high frame rate): its header is already unpacked
            peaks = np.frombuffer(buf, dtype="<f8", count=n_pk, offset=pos + HEADER_SIZE + length)
            blocks.append(
                PeakBlock(
                    np.array([t_int + t_frac * 1e-9]),
                    np.array([serial], np.uint64),
                    counts,
                    peaks.astype(np.float64).reshape(1, n_pk),
                )
            )
            pos += frame_len
            continue
        raw = np.frombuffer(buf, dtype=np.uint8, count=n_max * frame_len, offset=pos)
        raw = raw.reshape(n_max, frame_len)
        # A run continues while the layout bytes (outer header and counts) are identical.
        layout = np.concatenate(
            [raw[:, : HEADER_SIZE + 4], raw[:, HEADER_SIZE + PEAK_HEADER_SIZE : HEADER_SIZE + length]], axis=1
        )
        same = np.all(layout == layout[0], axis=1)
        n = n_max if same.all() else int(np.argmin(same))
        # the fields are copied out (astype), so nothing keeps a view of the caller's buffer
        rec = np.frombuffer(buf, dtype=_frame_dtype(n_ch, n_pk), count=n, offset=pos)
        peaks = rec["peaks"].astype(np.float64) if n_pk else np.zeros((n, 0))
        ts = rec["t_int"] + rec["t_frac"] * 1e-9  # float64
        blocks.append(PeakBlock(ts, rec["serial"].astype(np.uint64), counts, peaks))
        pos += n * frame_len
    return blocks, pos


class PeakStreamDecoder:
    """Bytes of the peak stream in, decoded blocks out, with a bounded buffer.

    ``feed`` appends what the socket gave and returns every complete frame; between calls at
    most ``limits.max_frame_bytes - 1`` bytes (the start of the next frame) are kept. A
    corrupt header raises :class:`HyperionError`; the stream is then lost (the caller drops the
    link), as no frame boundary can be trusted after it.
    """

    def __init__(self, limits: FrameLimits = DEFAULT_LIMITS):
        self.limits = limits
        self._buffer = bytearray()

    @property
    def buffered(self) -> int:
        """Bytes kept for the next frame."""
        return len(self._buffer)

    def feed(self, data: bytes) -> list[PeakBlock]:
        """Add received bytes; return the peak blocks of every frame now complete."""
        self._buffer += data
        try:
            blocks, used = decode_peak_frames(self._buffer, self.limits)
        except HyperionError as exc:
            # a new buffer, not clear(): the traceback still holds a view of the old one. The
            # decoder's finished frame in that traceback is emptied too, so the old buffer (up
            # to a frame plus a read) goes now rather than whenever the exception is collected.
            self._buffer = bytearray()
            traceback.clear_frames(exc.__traceback__)
            del data
            raise
        if used:
            del self._buffer[:used]
        return blocks


# --------------------------------------------------------------------------- client
class HyperionClient:
    """Asyncio client of one Hyperion instrument (command and peak-stream connections).

    ``limits`` bounds the frames the peak stream may announce (:class:`FrameLimits`); unless
    given, its channel count is the instrument's own (``#GetDutChannelCount``, asked when the
    command port answers before the stream is opened), else :data:`DEFAULT_CHANNELS`.
    """

    def __init__(
        self,
        host: str,
        command_port: int = COMMAND_PORT,
        stream_port: int = STREAM_PORT,
        timeout_s: float = 2.0,
        limits: FrameLimits | None = None,
    ):
        self.host = host
        self.command_port = command_port
        self.stream_port = stream_port
        self.timeout_s = timeout_s
        self.limits = limits or DEFAULT_LIMITS
        self._limits_given = limits is not None
        self._cmd: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._stream: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._decoder = PeakStreamDecoder(self.limits)

    async def command(self, command: str, argument: str | bytes = b"") -> tuple[bytes, bytes]:
        """Send one command, return (message, content); raise HyperionError on a bad status."""
        if self._cmd is None:
            self._cmd = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.command_port), self.timeout_s
            )
        reader, writer = self._cmd
        try:
            writer.write(encode_request(command, argument))
            await writer.drain()
            status, _, message, content = await asyncio.wait_for(read_response(reader), self.timeout_s)
        except (TimeoutError, HyperionError, OSError, asyncio.IncompleteReadError):
            # no answer boundary can be trusted any more: the next command reconnects
            self._cmd = None
            writer.close()
            raise
        if status != 0:
            raise HyperionError(f"{command}: {message.decode('ascii', 'replace')}")
        return message, content

    async def serial_number(self) -> str:
        """The instrument's serial number (``#GetSerialNumber``)."""
        return (await self.command("#GetSerialNumber"))[1].decode("ascii", "replace")

    async def channel_count(self) -> int:
        """The instrument's channel count; it also bounds the stream's frames from now on."""
        count = int(struct.unpack("<I", (await self.command("#GetDutChannelCount"))[1][:4])[0])
        if not self._limits_given and 1 <= count <= MAX_CHANNELS:
            self.limits = FrameLimits(count, self.limits.peaks_per_channel)
        return count

    async def is_ready(self) -> bool:
        """Whether the instrument says it is ready (``#isready``)."""
        return bool((await self.command("#isready"))[1][:1] == b"\x01")

    @property
    def buffered_bytes(self) -> int:
        """Bytes of the peak stream received but not yet decoded (less than one frame)."""
        return self._decoder.buffered

    async def open_stream(self) -> None:
        """Connect to the peak stream port (reading the channel count first, when it is
        not given, so the frames are bounded by it).
        """
        if self._cmd is not None and not self._limits_given:
            # on no (or a garbled) answer the default channel count is kept
            with contextlib.suppress(
                TimeoutError, OSError, HyperionError, asyncio.IncompleteReadError, struct.error
            ):
                await self.channel_count()
        self._stream = await asyncio.wait_for(
            asyncio.open_connection(self.host, self.stream_port), self.timeout_s
        )
        self._decoder = PeakStreamDecoder(self.limits)

    async def read_blocks(self, timeout_s: float | None = None) -> list[PeakBlock]:
        """Wait for data on the peak stream and return every complete frame received so far.

        Raises ConnectionError when the instrument closes the stream, TimeoutError when no
        complete frame arrives within ``timeout_s`` (bytes that never make a frame do not keep
        the link alive), HyperionError as soon as a corrupt header arrives.
        """
        if self._stream is None:
            raise ConnectionError("peak stream is not open")
        reader = self._stream[0]
        chunk = b""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + (timeout_s or self.timeout_s)
        try:
            while True:
                remaining = deadline - loop.time()
                if remaining <= 0:
                    raise TimeoutError()
                chunk = await asyncio.wait_for(reader.read(READ_SIZE), remaining)
                if not chunk:
                    raise ConnectionError("instrument closed the peak stream")
                blocks = self._decoder.feed(chunk)
                if blocks:
                    return blocks
        finally:
            # An exception raised here keeps this frame alive in its traceback, and asyncio
            # puts that traceback in a reference cycle (the awaiting future holds the exception,
            # the exception its traceback, the traceback wait_for's frame and that future):
            # the reader and its receive buffer (hundreds of KiB) would then live until the
            # cyclic collector runs. Dropping them from the frame lets close() free them at once.
            del reader, chunk

    async def close(self) -> None:
        """Close the command and stream connections (waiting at most 1 s for each)."""
        for conn in (self._cmd, self._stream):
            if conn is not None:
                conn[1].close()
                with contextlib.suppress(TimeoutError, OSError):
                    await asyncio.wait_for(conn[1].wait_closed(), 1.0)
        self._cmd = self._stream = None
