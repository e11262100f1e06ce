"""The configured outputs of a daemon: one publisher per [[udp]], [[serial]], [[mavlink]],
[natnet], [[vrpn]] table and the Zenoh poses, each serial line's rate checked against it."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from calibkit.core.errors import UserError
from daemon.config.mocapd import Config
from daemon.publish.line import fit_mavlink, fit_serial
from daemon.publish.mavlink import MavlinkPublisher
from daemon.publish.natnet import NatNetPublisher
from daemon.publish.serial import SerialPublisher
from daemon.publish.udp import UdpPublisher
from daemon.publish.vrpn import VrpnPublisher
from daemon.publish.zenoh_poses import ZenohPosePublisher

log = logging.getLogger("mocapd")


def make_publishers(config: Config, bodies=(), markerset=None, control=None, hub=None,
                    running=()) -> list:
    """The configured outputs; `bodies` (BodyDef) name the trackers NatNet and VRPN serve,
    `markerset` (the live MarkerSet, if any) the labelled markers NatNet describes,
    `control` (Daemon.handle) is how NatNet's StartRecording records, `hub` (the nodes'
    Zenoh session) is where the poses go out over Zenoh. An output of `running` (a reload's
    current outputs) whose settings are unchanged is kept as it is: its clients, sockets
    and thread go on, and the reload starts and stops only what changed."""
    pubs = []
    fps = config.sim.fps if config.sim is not None else config.fps
    shapes = _fingerprint([(b.name, b.id, b.markers, b.pivot) for b in bodies])
    described = None if markerset is None else (markerset.name, list(markerset.labels))

    def keep(spec, make):
        spec = _fingerprint(spec)
        for p in running:
            if getattr(p, "spec", None) == spec and p not in pubs:
                pubs.append(p)
                return
        pub = make()
        pub.spec = spec
        pubs.append(pub)

    for u in config.udp:
        keep(("udp", u), lambda u=u: UdpPublisher(
            [(u.host, u.port)], ttl=u.ttl, rate_hz=u.rate_hz, bodies=u.bodies,
            name=f"udp:{u.host}:{u.port}", interface=u.interface, markers=u.markers))
    for i, s in enumerate(config.serial):
        n = sum(1 for b in bodies if s.bodies is None or b.id in s.bodies)
        s = _fitted(f"serial[{i}] ({s.device})", fit_serial, s, n, fps)
        keep(("serial", s), lambda s=s: SerialPublisher(s.device, s.baud, s.rate_hz, s.bodies))
    for i, m in enumerate(config.mavlink):
        m = _fitted(f"mavlink[{i}] ({m.device})", fit_mavlink, m, fps)
        keep(("mavlink", m), lambda m=m: MavlinkPublisher(
            m.device, m.body, m.baud, m.rate_hz, m.message, m.frame, m.system_id,
            m.component_id, origin=m.origin))
    if config.natnet is not None:
        n = config.natnet
        keep(("natnet", n, shapes, described, fps), lambda: NatNetPublisher(
            bodies, n.interface, n.command_port, n.data_port, n.multicast, n.group,
            n.up_axis, n.ttl, n.rate_hz, n.legacy_unlabeled, name=f"natnet:{n.interface}",
            marker_sets=n.marker_sets, markerset=described, markerset_id=n.markerset_id,
            fps=fps, record_dir=n.record_dir, control=control, record_from=n.record_from,
            record_max_s=n.record_max_s, record_max_mb=n.record_max_mb))
    for v in config.vrpn:
        keep(("vrpn", v, shapes), lambda v=v: VrpnPublisher(
            bodies, v.host, v.port, v.rate_hz, v.udp, name=f"vrpn:{v.host}:{v.port}"))
    if hub is not None and config.zenoh.poses:
        keep(("zenoh", id(hub), shapes), lambda: ZenohPosePublisher(hub, bodies))
    return pubs


def _fingerprint(value):
    """A value made comparable with ==: arrays by their bytes, dataclasses field by field."""
    if isinstance(value, np.ndarray):
        return ("array", value.shape, value.dtype.str, value.tobytes())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return (type(value).__name__, *(_fingerprint(getattr(value, f.name))
                                        for f in dataclasses.fields(value)))
    if isinstance(value, (list, tuple)):
        return tuple(_fingerprint(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((k, _fingerprint(v)) for k, v in value.items()))
    if isinstance(value, (set, frozenset)):
        return tuple(sorted(value))
    return value


def _fitted(name: str, fit, out, *args):
    """An output's rate checked against its serial line (daemon.publish.line); a rate
    that cannot fit is the user's to fix (UserError)."""
    try:
        out, note = fit(out, *args)
    except ValueError as exc:
        raise UserError(f"{name}: {exc}") from None
    if note:
        log.info("%s: %s", name, note)
    return out
