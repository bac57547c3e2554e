"""MAVLink 2 message signing: who may speak on a link that more than our vehicles reach.

The signature is the first 6 bytes of SHA-256(secret key + the packet up to the
signature), after a link id and a 48-bit timestamp (10 us units since 1 January 2015).
A packet is taken only if it is signed, its signature is right, and its timestamp is
newer than the last one taken on its stream (link id, system, component); a stream seen
for the first time must be at most a minute behind the receiver's clock. Unlike
pymavlink's own check, a stream's timestamp moves only for a packet whose signature is
right, so one forged packet with a far-future time cannot shut the stream out.

The receiver's clock is the packet's receive time: the wall clock live, the recorded
time in a replay, so a replay judges the packets as the live run did.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path

from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.mavlink import SIGNED_FLAG, STX_V2, TlogWriter, header

EPOCH_2015_S = 1_420_070_400.0
"""1 January 2015 00:00 UTC [s since the Unix epoch]: the signing timestamps' zero."""
TICKS_PER_S = 100_000
"""Signing timestamps count 10 us."""
NEW_STREAM_TICKS = 60 * TICKS_PER_S
"""A new stream may be at most a minute behind the receiver's clock."""
SIGNATURE_BYTES = 13
"""Link id (1), timestamp (6), signature (6)."""


def timestamp_now(t_unix_s: float) -> int:
    """A signing timestamp [10 us since 2015] of a Unix time [s]."""
    return int((t_unix_s - EPOCH_2015_S) * TICKS_PER_S)


def load_key(path: str | Path) -> bytes:
    """The 32-byte secret key in a key file: 64 hexadecimal digits, or else a passphrase
    whose SHA-256 is the key (as MAVProxy's `signing setup PASSPHRASE` makes it)."""
    text = Path(path).read_text(encoding="utf-8").strip()
    if not text:
        raise ValueError(f"{path}: empty key file")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    return key if len(key) == 32 else hashlib.sha256(text.encode("utf-8")).digest()


class Verdict(StrEnum):
    SIGNED = "signed"
    UNSIGNED = "unsigned"
    FORGED = "bad_signature"
    REPLAYED = "replayed"


class SignatureCheck:
    """The receiving end's check (one per link)."""

    def __init__(self, key: bytes) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")
        self._key = key
        self._streams: dict[tuple[int, int, int], int] = {}

    def __repr__(self) -> str:
        return "SignatureCheck(<key withheld>)"

    def check(self, packet: bytes, t_recv_s: float) -> Verdict:
        """The verdict on one packet that passed its CRC."""
        if packet[0] != STX_V2 or not packet[2] & SIGNED_FLAG or len(packet) < SIGNATURE_BYTES:
            return Verdict.UNSIGNED
        mac = hashlib.sha256(self._key + packet[:-6]).digest()[:6]
        if not hmac.compare_digest(mac, packet[-6:]):
            return Verdict.FORGED
        stamp = int.from_bytes(packet[-12:-6], "little")
        _, sysid, compid = header(packet)
        stream = (packet[-13], sysid, compid)
        last = self._streams.get(stream)
        if last is not None:
            if stamp <= last:
                return Verdict.REPLAYED
        elif stamp + NEW_STREAM_TICKS < timestamp_now(t_recv_s):
            return Verdict.REPLAYED
        self._streams[stream] = stamp
        return Verdict.SIGNED


def sign_outgoing(mav: object, key: bytes, t_unix_s: float, link_id: int = 0) -> None:
    """Make a pymavlink MAVLink object sign what it sends (and refuse unsigned packets it
    parses), its timestamps starting from t_unix_s."""
    signing = mav.signing  # type: ignore[attr-defined]
    signing.secret_key = key
    signing.sign_outgoing = True
    signing.link_id = link_id
    signing.timestamp = timestamp_now(t_unix_s)


class SigningGate:
    """A link's signature check with what it does with the packets that fail it: count
    them by why, say so once, and record them apart from the estimate's recording."""

    def __init__(
        self,
        key: bytes,
        health: LinkHealth,
        report_once: Callable[[str, str], None],
        rejected_path: Path | None = None,
    ) -> None:
        self.key = key
        self.check = SignatureCheck(key)
        self.health = health
        self.report_once = report_once
        self.rejected_path = rejected_path
        self.rejected: TlogWriter | None = None
        """The file of rejected packets, opened at the first one."""

    def passes(self, packet: bytes, t_recv_s: float, name: str) -> bool:
        """Whether a packet passes the signature check; else it is counted by why,
        dropped, and recorded apart (rejected_path), not in the recording the estimate is
        made of. The check's state moves only with good packets, so a replay of the
        recording with the key accepts what the live run accepted. The rejected file is
        for forensics: replayed alone, a replayed copy there looks fresh."""
        verdict = self.check.check(packet, t_recv_s)
        if verdict == Verdict.SIGNED:
            return True
        counts = self.health.counts(name)
        setattr(counts, verdict.value, getattr(counts, verdict.value) + 1)
        where = ""
        if self.rejected_path is not None:
            if self.rejected is None:
                self.rejected = TlogWriter(self.rejected_path)
            self.rejected.write(int(round(t_recv_s * 1e6)), packet)
            where = f", recorded to {self.rejected_path}"
        self.report_once(
            f"sign-{verdict.value}",
            f"{verdict.value.replace('_', ' ')} packet(s) with signing on: dropped{where}",
        )
        return False
