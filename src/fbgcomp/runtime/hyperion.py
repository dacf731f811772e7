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
"""

from __future__ import annotations

import asyncio
import functools
import struct
from dataclasses import dataclass

import numpy as np

COMMAND_PORT = 51971
STREAM_PORT = 51972

HEADER = struct.Struct("<BBHI")          # 8 bytes, request and response
PEAK_HEADER = struct.Struct("<HHIQII")   # 24 bytes
HEADER_SIZE = HEADER.size
PEAK_HEADER_SIZE = PEAK_HEADER.size
PEAK_HEADER_VERSION = 1


class HyperionError(Exception):
    """The instrument answered a command with a non-zero status, or the stream is corrupt."""


# --------------------------------------------------------------------------- command port
def encode_request(command: str, argument: str | bytes = b"", request_options: int = 0) -> bytes:
    """Bytes of one command-port request."""
    cmd = command.encode("ascii")
    arg = argument.encode("ascii") if isinstance(argument, str) else bytes(argument)
    return HEADER.pack(request_options, 0, len(cmd), len(arg)) + cmd + arg


def encode_response(message: str | bytes = b"", content: bytes = b"", status: int = 0,
                    response_type: int = 0) -> bytes:
    """Bytes of one command-port response (also the outer header of a stream frame)."""
    msg = message.encode("ascii") if isinstance(message, str) else bytes(message)
    return HEADER.pack(status, response_type, len(msg), len(content)) + msg + content


async def read_request(reader: asyncio.StreamReader) -> tuple[int, str, bytes]:
    """Read one request: (request_options, command, argument). Raises IncompleteReadError at EOF."""
    options, _, cmd_len, arg_len = HEADER.unpack(await reader.readexactly(HEADER_SIZE))
    cmd = (await reader.readexactly(cmd_len)).decode("ascii", "replace")
    arg = await reader.readexactly(arg_len) if arg_len else b""
    return options, cmd, arg


async def read_response(reader: asyncio.StreamReader) -> tuple[int, int, bytes, bytes]:
    """Read one response: (status, response_type, message, content)."""
    status, rtype, msg_len, content_len = HEADER.unpack(await reader.readexactly(HEADER_SIZE))
    message = await reader.readexactly(msg_len) if msg_len else b""
    content = await reader.readexactly(content_len) if content_len else b""
    return status, rtype, message, content


# --------------------------------------------------------------------------- peak stream
def encode_peak_frame(serial_number: int, timestamp_s: float, peak_counts: np.ndarray,
                      wavelengths_nm: np.ndarray) -> bytes:
    """Bytes of one streamed peak frame (outer header + peak header + counts + peaks).

    ``peak_counts`` holds one int16 count per channel, ``wavelengths_nm`` the concatenated
    peaks of all channels in channel order (``sum(peak_counts)`` values).
    """
    counts = np.asarray(peak_counts, dtype="<i2")
    peaks = np.asarray(wavelengths_nm, dtype="<f8")
    length = PEAK_HEADER_SIZE + counts.nbytes
    t_int = int(timestamp_s)
    t_frac_ns = int(round((timestamp_s - t_int) * 1e9))
    if t_frac_ns >= 1_000_000_000:
        t_int, t_frac_ns = t_int + 1, t_frac_ns - 1_000_000_000
    content = (PEAK_HEADER.pack(length, PEAK_HEADER_VERSION, 0, serial_number, t_int, t_frac_ns)
               + counts.tobytes() + peaks.tobytes())
    return HEADER.pack(0, 0, 0, len(content)) + content


def encode_peak_frames(serial_number: int, timestamps_s: np.ndarray, peak_counts: np.ndarray,
                       wavelengths_nm: np.ndarray) -> bytes:
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
    fields = [("status", "u1"), ("rtype", "u1"), ("msg_len", "<u2"), ("content_length", "<u4"),
              ("length", "<u2"), ("version", "<u2"), ("reserved", "<u4"), ("serial", "<u8"),
              ("t_int", "<u4"), ("t_frac", "<u4")]
    if n_channels:
        fields.append(("counts", "<i2", (n_channels,)))
    if n_peaks:
        fields.append(("peaks", "<f8", (n_peaks,)))
    return np.dtype(fields)


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
        """Channel index (0-based) of every peak column."""
        return np.repeat(np.arange(self.peak_counts.size), np.maximum(self.peak_counts, 0))


def decode_peak_frames(buffer: bytes | bytearray | memoryview) -> tuple[list[PeakBlock], int]:
    """Decode every complete frame in ``buffer``.

    Returns the decoded blocks (runs of frames with identical layout) and the number of bytes
    consumed; the caller keeps the remaining bytes for the next read.
    """
    buf = memoryview(buffer).cast("B")
    total = len(buf)
    pos = 0
    blocks: list[PeakBlock] = []
    while total - pos >= HEADER_SIZE + PEAK_HEADER_SIZE:
        status, _, msg_len, content_len = HEADER.unpack_from(buf, pos)
        frame_len = HEADER_SIZE + msg_len + content_len
        if status != 0 or msg_len != 0:
            # Not a peak frame (an error message from the instrument): skip it whole.
            if total - pos < frame_len:
                break
            pos += frame_len
            continue
        if total - pos < frame_len:
            break
        length = PEAK_HEADER.unpack_from(buf, pos + HEADER_SIZE)[0]
        if length < PEAK_HEADER_SIZE or length > content_len or (length - PEAK_HEADER_SIZE) % 2 \
                or (content_len - length) % 8:
            raise HyperionError(f"corrupt peak frame: length={length}, content={content_len}")
        n_ch = (length - PEAK_HEADER_SIZE) // 2
        n_pk = (content_len - length) // 8
        n_max = (total - pos) // frame_len
        raw = np.frombuffer(buf, dtype=np.uint8, count=n_max * frame_len, offset=pos)
        raw = raw.reshape(n_max, frame_len)
        # A run continues while the layout bytes (outer header and counts) are identical.
        layout = np.concatenate([raw[:, :HEADER_SIZE + 4],
                                 raw[:, HEADER_SIZE + PEAK_HEADER_SIZE:HEADER_SIZE + length]], axis=1)
        same = np.all(layout == layout[0], axis=1)
        n = n_max if same.all() else int(np.argmin(same))
        rec = raw[:n].copy().view(_frame_dtype(n_ch, n_pk)).reshape(n)
        counts = rec["counts"][0].astype(np.int16) if n_ch else np.zeros(0, np.int16)
        if int(np.maximum(counts, 0).sum()) != n_pk:
            raise HyperionError(f"corrupt peak frame: counts sum {counts.sum()} != {n_pk} peaks")
        peaks = rec["peaks"].astype(np.float64) if n_pk else np.zeros((n, 0))
        ts = rec["t_int"].astype(np.float64) + rec["t_frac"].astype(np.float64) * 1e-9
        blocks.append(PeakBlock(ts, rec["serial"].astype(np.uint64), counts, peaks))
        pos += n * frame_len
    return blocks, pos


# --------------------------------------------------------------------------- client
class HyperionClient:
    """Asyncio client of one Hyperion instrument (command and peak-stream connections)."""

    def __init__(self, host: str, command_port: int = COMMAND_PORT,
                 stream_port: int = STREAM_PORT, timeout_s: float = 2.0):
        self.host = host
        self.command_port = command_port
        self.stream_port = stream_port
        self.timeout_s = timeout_s
        self._cmd: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._stream: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._buffer = bytearray()

    async def command(self, command: str, argument: str | bytes = b"") -> tuple[bytes, bytes]:
        """Send one command, return (message, content); raise HyperionError on a bad status."""
        if self._cmd is None:
            self._cmd = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.command_port), self.timeout_s)
        reader, writer = self._cmd
        writer.write(encode_request(command, argument))
        await writer.drain()
        status, _, message, content = await asyncio.wait_for(read_response(reader), self.timeout_s)
        if status != 0:
            raise HyperionError(f"{command}: {message.decode('ascii', 'replace')}")
        return message, content

    async def serial_number(self) -> str:
        return (await self.command("#GetSerialNumber"))[1].decode("ascii", "replace")

    async def channel_count(self) -> int:
        return int(struct.unpack("<I", (await self.command("#GetDutChannelCount"))[1][:4])[0])

    async def is_ready(self) -> bool:
        return bool((await self.command("#isready"))[1][:1] == b"\x01")

    async def open_stream(self) -> None:
        self._stream = await asyncio.wait_for(
            asyncio.open_connection(self.host, self.stream_port), self.timeout_s)
        self._buffer.clear()

    async def read_blocks(self, timeout_s: float | None = None) -> list[PeakBlock]:
        """Wait for data on the peak stream and return every complete frame received so far.

        Raises ConnectionError when the instrument closes the stream, TimeoutError when
        nothing arrives within ``timeout_s``.
        """
        if self._stream is None:
            raise ConnectionError("peak stream is not open")
        reader = self._stream[0]
        while True:
            chunk = await asyncio.wait_for(reader.read(1 << 20), timeout_s or self.timeout_s)
            if not chunk:
                raise ConnectionError("instrument closed the peak stream")
            self._buffer += chunk
            blocks, used = decode_peak_frames(self._buffer)
            if used:
                del self._buffer[:used]
            if blocks:
                return blocks

    async def close(self) -> None:
        for conn in (self._cmd, self._stream):
            if conn is not None:
                conn[1].close()
                try:
                    await asyncio.wait_for(conn[1].wait_closed(), 1.0)
                except (OSError, asyncio.TimeoutError):
                    pass
        self._cmd = self._stream = None
