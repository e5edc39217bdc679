"""The crowd SLAM's keys on the wire (track, map/version, progress): how they match the existing ones,
and the access-control list on a real router with user/password authentication on loopback."""

import threading

import numpy as np
import pytest
import zenoh

from hybridloc.types import CorrectedTrack
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import MapVersion, Progress, Track
from hybridloc.wire.zconfig import Security, client_config, free_port, server_config

from .helpers import wait_until as _wait

SITE = "site1"


def test_new_keys_match_only_their_own_subscriptions():
    K = zenoh.KeyExpr
    track, version, progress = K(P.key_track(SITE, "dev01")), K(P.key_map_version(SITE)), K(P.key_progress(SITE))
    # the map queryable (hl/v1/*/map) is one chunk short of every map/version key
    assert not K(P.SUB_MAPS).intersects(version) and K(P.SUB_MAPS).intersects(K(P.key_map(SITE)))
    assert K(P.SUB_MAP_VERSIONS).intersects(version) and not K(P.SUB_MAP_VERSIONS).intersects(K(P.key_map(SITE)))
    assert K(P.SUB_TRACKS).intersects(track) and K(P.SUB_PROGRESS).intersects(progress)
    old = [P.SUB_BATCHES, P.SUB_LOCATE, P.SUB_MAPS, P.SUB_ALIVE, P.KEY_STATUS]
    for new in (track, version, progress):
        assert not any(K(k).intersects(new) for k in old), str(new)
    for new, sub in ((track, P.SUB_TRACKS), (version, P.SUB_MAP_VERSIONS), (progress, P.SUB_PROGRESS)):
        others = [K(k) for k in (P.SUB_TRACKS, P.SUB_MAP_VERSIONS, P.SUB_PROGRESS) if k != sub]
        assert not any(o.intersects(new) for o in others), str(new)
    # one device's track is not another's
    assert not K(f"{P.PREFIX}/*/dev02/track").intersects(track)
    with pytest.raises(ValueError):
        P.key_track(SITE, "*")  # a wildcard is not an id
    with pytest.raises(ValueError):
        P.key_map_version("a/b")


def _track(device: str, walk_id: int) -> bytes:
    tr = CorrectedTrack(walk_id, [1.0, 1.5], [[0.0, 0.0], [0.7, 0.0]], np.stack([np.eye(2) * 0.04] * 2), ("F1", "F1"), ("step", "step"), "map")
    return C.TRACK.encode(Track(SITE, device, walk_id, 1, 1, tr))


def test_acl_each_device_hears_its_own_track_and_every_announcement_but_no_other_track(tmp_path):
    """A router with usrpwd + the device ACL: the server puts both devices' tracks, a map version and a
    progress; each device gets its own track only (a spy subscription on the other's key and on every
    track gets nothing), both get the announcements, and a device's own put on ``map/version`` reaches
    no other device. The negative checks rely on order, not on sleeping: what a router forwards to a
    device arrives, over the one link, before what the router sends it later, and channel subscribers
    (no Python callback threads) keep that order."""
    users = tmp_path / "users.txt"
    users.write_text("server:srvpw\ndev01:pw1\ndev02:pw2\n")
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(server_config(ep, Security(users_file=str(users), acl_devices=["dev01", "dev02"])))
    try:
        with (
            zenoh.open(client_config(ep, Security(user="dev01", password="pw1"))) as s1,
            zenoh.open(client_config(ep, Security(user="dev02", password="pw2"))) as s2,
        ):
            sessions = {"dev01": s1, "dev02": s2}
            remote = zenoh.Locality.REMOTE  # a session hands its own puts to its own subscribers whatever the ACL says
            # announcements first, the own track last: once the router sees the track subscription
            # (matching below) it has seen the others (declarations travel in order)
            subs = {
                (d, kind): s.declare_subscriber(key, allowed_origin=remote)
                for d, s in sessions.items()
                for kind, key in (("version", P.key_map_version(SITE)), ("progress", P.key_progress(SITE)))
            }
            spies = [s2.declare_subscriber(P.key_track(SITE, "dev01")), s2.declare_subscriber(P.SUB_TRACKS)]
            for d, s in sessions.items():
                subs[(d, "track")] = s.declare_subscriber(P.key_track(SITE, d))
            pubs = {d: router.declare_publisher(P.key_track(SITE, d)) for d in sessions}
            assert _wait(lambda: all(p.matching_status.matching for p in pubs.values()))
            seen_pose = threading.Event()
            pose_sub = router.declare_subscriber(P.key_pose(SITE, "dev01"), lambda _s: seen_pose.set())

            s1.put(P.key_map_version(SITE), C.MAP_VERSION.encode(MapVersion(SITE, 99, "import", 0.0)))  # dev01 announcing a map
            s1.put(P.key_pose(SITE, "dev01"), b"{}")  # after it on the same link: once the router has this, it has dealt with the fake
            assert seen_pose.wait(10.0)
            pubs["dev01"].put(_track("dev01", 11))
            pubs["dev02"].put(_track("dev02", 12))
            version = C.MAP_VERSION.encode(MapVersion(SITE, 3, "slam", 1.7e9, 5, 0.5))
            progress = C.PROGRESS.encode(Progress(SITE, "solve", "F1", 2, 4, 1.7e9))
            router.put(P.key_map_version(SITE), version)
            router.put(P.key_progress(SITE), progress)

            got: dict = {k: [] for k in subs}

            def collect():
                for k, sub in subs.items():
                    while (smp := sub.try_recv()) is not None:
                        got[k].append(smp.payload.to_bytes())
                return all(got.values())

            assert _wait(collect), got
            spied = [str(smp.key_expr) for sp in spies for smp in iter(sp.try_recv, None)]
            for sub in [*subs.values(), *spies, pose_sub]:
                sub.undeclare()
            for pub in pubs.values():
                pub.undeclare()
        for d, walk in (("dev01", 11), ("dev02", 12)):
            assert [C.TRACK.decode(b, SITE, d).walk_id for b in got[(d, "track")]] == [walk]
            assert got[(d, "version")] == [version]  # the fake announcement reached neither device
            assert got[(d, "progress")] == [progress]
        # dev02 never received dev01's track, though it was put first (its wildcard got its own)
        assert spied == [P.key_track(SITE, "dev02")]
    finally:
        router.close()
