"""The turntable encoder line protocol (version 1), shared by the reader and the mock device.

ASCII lines ending in ``\\n``; every line carries an NMEA-style checksum: two upper-case
hex digits, the XOR of all bytes between the leading sigil and ``*``.

Banner (device -> host, on connect and in reply to ``HELLO``)::

    #GSENC,<version>,<counts_per_rev>,<device_name>*CK

Sample (device -> host, at the device's sample rate, e.g. 1 kHz)::

    $E,<seq>,<t_us>,<count>,<index>,<index_count>*CK

    seq          uint32, +1 per sample, wraps to 0 after 2**32-1 (gaps = lost lines)
    t_us         device clock, microseconds since device start (uint64)
    count        signed accumulated quadrature count (never wraps in practice)
    index        1 on the first sample after the index pulse, else 0
    index_count  count latched at the index pulse when index = 1, else empty

Host -> device commands: ``HELLO`` (answer: banner). Anything else is ignored by the device.

Example: ``$E,17,17000,70,0,*6E``.
"""

from __future__ import annotations

from dataclasses import dataclass

PROTOCOL_VERSION = 1
SEQ_MODULUS = 1 << 32


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


def parse_line(line: bytes) -> RawSample | Banner:
    """Parse one line (without or with its newline); raise ProtocolError when invalid."""
    sigil, f = _split(line)
    try:
        if sigil == "$" and f[0] == "E" and len(f) == 6:
            seq, t_us, count, idx = int(f[1]), int(f[2]), int(f[3]), int(f[4])
            if not (0 <= seq < SEQ_MODULUS) or t_us < 0 or idx not in (0, 1):
                raise ProtocolError(f"field out of range: {line[:60]!r}")
            ic = int(f[5]) if f[5] else None
            if idx == 1 and ic is None:
                raise ProtocolError(f"index=1 without index_count: {line[:60]!r}")
            return RawSample(seq, t_us, count, bool(idx), ic)
        if sigil == "#" and f[0] == "GSENC" and len(f) == 4:
            return Banner(int(f[1]), int(f[2]), f[3])
    except ValueError as exc:
        raise ProtocolError(f"bad number in {line[:60]!r}: {exc}") from exc
    raise ProtocolError(f"unknown line type: {line[:60]!r}")
