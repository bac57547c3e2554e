"""MAVLink 2 signing: with a key, the simulated vehicle signs and the station takes only
correctly signed, fresh packets; unsigned, forged and replayed ones are counted and kept
out of the estimate, live over real UDP and again in a replay of the recording."""

from __future__ import annotations

import hashlib
import io
import time
from pathlib import Path

import pytest

from gcs_estimator.config import AircraftConfig, ConfigError, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter, read_tlog
from gcs_estimator.ingest.telemetry.signing import (
    NEW_STREAM_TICKS,
    TICKS_PER_S,
    load_key,
    sign_outgoing,
    timestamp_now,
)
from gcs_estimator.runtime.decode_worker import WorkerTlogSource
from gcs_estimator.stop import Stop
from sim.truth import simulate
from tests.telemetry.test_link import SHORT, fly_to_station

KEY_HEX = "5e" * 32


def _config(tmp_path: Path) -> AircraftConfig:
    key_file = tmp_path / "key.txt"
    key_file.write_text(KEY_HEX + "\n")
    return load_config("noc_uav", [*SHORT, f'link.signing_key_file="{key_file}"'])


def _signer(key: bytes, t: float, sysid: int = 1) -> mavlink.Codec:
    codec = mavlink.Codec(sysid, 1)
    sign_outgoing(codec.mav, key, t)
    return codec


def test_signed_flight_over_udp_is_estimated_with_nothing_rejected(tmp_path: Path) -> None:
    config = _config(tmp_path)
    fl = simulate(config, seed=2)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    station = fly_to_station(config, [rec], speed=0.0, record=None)
    h = station.link.health.total()
    assert (h.unsigned, h.bad_signature, h.replayed) == (0, 0, 0)
    assert station.frames() == len(fl.t_s)
    cma = config.coefficient_names.index("Cma")
    assert station.final()["IEKF"][cma] == pytest.approx(fl.truth[cma], rel=0.1)


def test_unsigned_forged_and_replayed_packets_are_counted_and_dropped(tmp_path: Path) -> None:
    config = _config(tmp_path)
    key = load_key(config.link.signing_key_file)
    here = ("127.0.0.1", 5000)
    t0 = time.time()
    good, plain = _signer(key, t0), mavlink.Codec(1, 1)
    forger = _signer(bytes(32), t0 + 3600)  # another key, an hour ahead
    stale = _signer(key, t0 - 2 * NEW_STREAM_TICKS / TICKS_PER_S, sysid=2)
    stale.mav.signing.link_id = 7  # a stream never seen, two minutes old
    hb = mavlink.MAV_TYPE_FIXED_WING
    first = good.heartbeat(hb)
    sent = [
        (first, t0),
        (plain.heartbeat(hb), t0 + 0.1),  # unsigned
        (forger.heartbeat(hb), t0 + 0.2),  # wrong key, far-future time
        (good.heartbeat(hb), t0 + 0.3),  # still taken: the forgery moved nothing
        (first, t0 + 0.4),  # replayed
        (stale.heartbeat(hb), t0 + 0.5),  # a new stream too old
    ]
    tlog, rejected = tmp_path / "signed.tlog", tmp_path / "signed.rejected.tlog"
    log = io.StringIO()
    link = MavlinkLink(config.link, recorder=TlogWriter(tlog), log=log, rejected_path=rejected)
    for packet, t in sent:
        list(link.datagram(packet, t, here))
    link.close()
    counts = link.health.total()
    assert (counts.received, counts.unsigned, counts.bad_signature, counts.replayed) == (
        2,
        1,
        1,
        2,
    )
    assert 2 not in link.vehicles  # the stale stream's vehicle never appeared
    # The estimate's recording holds what was accepted; the rest is kept apart, as sent.
    assert [(r.packet, r.t_recv_us) for r in read_tlog(tlog)] == [
        (p, round(t * 1e6)) for p, t in (sent[0], sent[3])
    ]
    assert [r.packet for r in read_tlog(rejected)] == [p for p, _ in (sent[1:3] + sent[4:])]
    assert str(rejected) in log.getvalue()

    for kind in (TlogSource, WorkerTlogSource):  # a replay with the key accepts the same
        source = kind([tlog], MavlinkLink(config.link, log=io.StringIO()))
        list(source.frames(Stop()))
        stats = source.link_stats()
        source.close()
        got = [stats[k] for k in ("received", "unsigned", "bad_signature", "replayed")]
        assert got == [2, 0, 0, 0]


def test_the_station_signs_and_the_vehicle_refuses_the_unsigned(tmp_path: Path) -> None:
    config = _config(tmp_path)
    key = load_key(config.link.signing_key_file)
    station = mavlink.Codec(mavlink.GCS_SYSTEM_ID, mavlink.GCS_COMPONENT_ID)
    MavlinkLink(config.link).sign(station, time.time())
    signed = station.set_message_interval(1, "ATTITUDE", 25.0)
    assert signed[2] & mavlink.SIGNED_FLAG
    vehicle = _signer(key, time.time())
    assert [m.get_type() for m in vehicle.parse(signed)] == ["COMMAND_LONG"]
    unsigned = mavlink.Codec(255, 190).set_message_interval(1, "ATTITUDE", 25.0)
    assert "COMMAND_LONG" not in [m.get_type() for m in vehicle.parse(unsigned)]


def test_keys_from_hex_or_passphrase_and_a_missing_file_named(tmp_path: Path) -> None:
    hex_file, phrase_file = tmp_path / "hex", tmp_path / "phrase"
    hex_file.write_text(KEY_HEX)
    phrase_file.write_text("correct horse battery staple\n")
    assert load_key(hex_file) == bytes.fromhex(KEY_HEX)
    assert load_key(phrase_file) == hashlib.sha256(b"correct horse battery staple").digest()
    config = load_config("noc_uav", [f'link.signing_key_file="{tmp_path / "absent"}"'])
    with pytest.raises(ConfigError, match=r"link\.signing_key_file: .*absent"):
        MavlinkLink(config.link)
    assert timestamp_now(1_420_070_400.0 + 1.0) == TICKS_PER_S
