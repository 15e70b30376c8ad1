"""The turntable encoder line protocol (version 1), shared by the reader and the mock device.

ASCII lines ending in ``\\n``; every line carries an NMEA-style checksum: two upper-case
hex digits, the XOR of all bytes between the leading sigil and ``*``.

Banner (device -> host, on connect and in reply to ``HELLO``)::

    #GSENC,<version>,<counts_per_rev>,<device_name>*CK

Sample (device -> host, at the device's sample rate, e.g. 1 kHz)::

    $E,<seq>,<t_us>,<count>,<index>,<index_count>*CK

    seq          uint32, +1 per sample, wraps to 0 after 2**32-1 (gaps = lost lines)
    t_us         device clock, microseconds since device start, 0 <= t_us <= (2**63-1) // 1000
                 (292 years: the host keeps device time as int64 nanoseconds)
    count        signed accumulated quadrature count, int64 (never wraps in practice; a device whose counter is
                 16, 24 or 32 bits wide and wraps is continued by the reader, EncoderReader._unwrap_count)
    index        1 on the first sample after the index pulse, else 0
    index_count  count latched at the index pulse when index = 1 (int64), else empty

A line with a field outside its range is invalid like one with a bad checksum: the parser
raises :class:`ProtocolError` and the reader counts it as corrupt.

Host -> device commands: ``HELLO`` (answer: banner). Anything else is ignored by the device.

Example: ``$E,17,17000,70,0,*6E``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from gearscan.core.types import ENCODER_COUNT_MAX, ENCODER_SEQ_MODULUS, ENCODER_TIME_US_MAX

PROTOCOL_VERSION = 1
SEQ_MODULUS = ENCODER_SEQ_MODULUS


class ProtocolError(ValueError):
    """A line that is not a valid protocol line (bad checksum, fields, sigil)."""


def checksum(body: bytes) -> str:
    x = 0
    for b in body:
        x ^= b
    return f"{x:02X}"


def frame_line(sigil: str, body: str) -> bytes:
    """``sigil + body + '*' + checksum + '\\n'`` as bytes."""
    raw = body.encode("ascii")
    return sigil.encode() + raw + b"*" + checksum(raw).encode() + b"\n"


@dataclass(frozen=True, slots=True)
class Banner:
    version: int
    counts_per_rev: int
    device: str

    def encode(self) -> bytes:
        return frame_line("#", f"GSENC,{self.version},{self.counts_per_rev},{self.device}")


@dataclass(frozen=True, slots=True)
class RawSample:
    seq: int
    t_us: int
    count: int
    index: bool
    index_count: int | None

    def encode(self) -> bytes:
        ic = "" if self.index_count is None else str(self.index_count)
        return frame_line("$", f"E,{self.seq},{self.t_us},{self.count},{int(self.index)},{ic}")


def _split(line: bytes) -> tuple[str, list[str]]:
    line = line.strip()
    if len(line) < 5 or line[:1] not in (b"$", b"#"):
        raise ProtocolError(f"no sigil or too short: {line[:40]!r}")
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 3:
        raise ProtocolError(f"no checksum: {line[:40]!r}")
    body, ck = line[1:star], line[star + 1 :]
    if checksum(body) != ck.decode("ascii", "replace").upper():
        raise ProtocolError(f"checksum {ck!r} != {checksum(body)}: {line[:40]!r}")
    try:
        return line[:1].decode(), body.decode("ascii").split(",")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"non-ASCII bytes: {line[:40]!r}") from exc


_INT = re.compile(r"-?[0-9]{1,20}")


def _int(field: str) -> int:
    """A decimal integer as the device writes it (no spaces, '+' or '_', at most 20 digits)."""
    if not _INT.fullmatch(field):
        raise ValueError(f"invalid integer {field[:24]!r}")
    return int(field)


def parse_line(line: bytes) -> RawSample | Banner:
    """Parse one line (without or with its newline); raise ProtocolError when invalid."""
    sigil, f = _split(line)
    try:
        if sigil == "$" and f[0] == "E" and len(f) == 6:
            seq, t_us, count, idx = _int(f[1]), _int(f[2]), _int(f[3]), _int(f[4])
            ic = _int(f[5]) if f[5] else None
            for name, value, ok in (
                ("seq", seq, 0 <= seq < SEQ_MODULUS),
                ("t_us", t_us, 0 <= t_us <= ENCODER_TIME_US_MAX),
                ("count", count, abs(count) <= ENCODER_COUNT_MAX),
                ("index", idx, idx in (0, 1)),
                ("index_count", ic, ic is None or abs(ic) <= ENCODER_COUNT_MAX),
            ):
                if not ok:
                    raise ProtocolError(f"{name} = {value} out of range: {line[:60]!r}")
            if idx == 1 and ic is None:
                raise ProtocolError(f"index=1 without index_count: {line[:60]!r}")
            return RawSample(seq, t_us, count, bool(idx), ic)
        if sigil == "#" and f[0] == "GSENC" and len(f) == 4:
            version, cpr = _int(f[1]), _int(f[2])
            if version < 0 or not 0 < cpr <= ENCODER_COUNT_MAX:
                raise ProtocolError(f"banner version {version} or counts_per_rev {cpr} out of range: {line[:60]!r}")
            return Banner(version, cpr, f[3])
    except ProtocolError:
        raise
    except ValueError as exc:
        raise ProtocolError(f"bad number in {line[:60]!r}: {exc}") from exc
    raise ProtocolError(f"unknown line type: {line[:60]!r}")
