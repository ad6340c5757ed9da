"""Zenoh sessions, segment publishers and subscribers, liveliness.

Defaults (:class:`SessionSettings`): peer mode, listening on ``tcp/127.0.0.1:<free port>``
only, multicast scouting off, optional connect endpoints.  Nothing listens on anything but
127.0.0.1 unless configured.  Link timing: a BLOCK put waits up to
:data:`BLOCK_WAIT_BEFORE_CLOSE` for a congested link and a link lives
:data:`LEASE` without news (Zenoh's 5 s and 10 s lost stalled consumers).

``ttl run`` starts its stages in **client** mode behind the launcher's router: every
segment goes through the router, and a client whose link closed reconnects and
re-declares its subscriptions.  Peers talking directly do not re-establish a closed
peer-to-peer link, and a router does not route between two peers (measured with
zenoh 1.10: a consumer stopped for 9 s never received another segment).

With ``credentials`` (a directory of :mod:`streamer.bus.security`) and an ``identity``, a
session talks mutual TLS only (``transport/link/tls``, ``enable_mtls``, TLS the only link
protocol) with that identity's certificate, and a router also enforces the pipeline's
access-control list; ``ttl run`` does this for every session of a run.

A Zenoh configuration file (JSON5, Zenoh's own format, see
``streamer/configs/*.json5``) selects client or router mode and the endpoints of a
deployment over several hosts; what the file leaves unset keeps the safe defaults above
(loopback listening, no multicast scouting), and explicit :class:`SessionSettings`
fields override the file.

Segment data go through the advanced publishers and subscribers of
:mod:`streamer.bus.segment_stream`.

:class:`Bus` wraps a session as a context manager that undeclares everything declared
through it (a callback subscriber left declared otherwise hangs the interpreter at exit)
and closes the session.
"""

from __future__ import annotations

import json
import logging
import socket
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from .access_control import access_control
from .keys import alive_key, alive_pattern, parse_alive_key
from .security import CredentialsError, Identity
from .segment_stream import (
    DEFAULT_CACHE,
    SegmentPublisher,
    SegmentSubscription,
    declare_segment_subscriber,
    refetch_segment,
)

log = logging.getLogger(__name__)

#: The only address listened on by default.
LOOPBACK = "127.0.0.1"
#: Default router endpoint (Zenoh's customary port, on loopback).
DEFAULT_ROUTER_LISTEN = ("tcp/127.0.0.1:7447",)
MODES = ("peer", "client", "router")
#: How long a BLOCK put may wait for a congested link before Zenoh closes the link [s].
#: Zenoh's default, 5 s, closed the link of a consumer starved of CPU for a few seconds
#: (a loaded 2-core machine), and a closed peer-to-peer link is never re-established.
#: It must stay below the lease: zenoh 1.10 never wakes a BLOCK put whose link was closed
#: by lease expiry while it waited (measured: the publisher hangs for ever).
BLOCK_WAIT_BEFORE_CLOSE = 30.0
#: Link lease [s] (Zenoh's default 10 s): a process silent that long loses its links.
LEASE = 60.0
#: How long a client keeps trying to reach its router when the session opens [s]
#: (Zenoh's default for clients: one attempt), so that a stage may start before the router.
CLIENT_CONNECT_TIMEOUT = 30.0


class SessionConfigError(ValueError):
    """A session setting or configuration file is invalid (message names it)."""


@dataclass(frozen=True)
class SessionSettings:
    """How to open a Zenoh session.

    Every field left None takes its value from ``config_file`` when the file sets it,
    else the safe default.

    Attributes
    ----------
    mode : {"peer", "client", "router"}, optional
        Default "peer".
    listen : sequence of str, optional
        Endpoints to listen on.  Default: ``tcp/127.0.0.1:<free port>`` (peer, router),
        none (client).
    connect : sequence of str, optional
        Endpoints to connect to (routers or peers), e.g. ``tcp/127.0.0.1:7447``.
    multicast_scouting : bool, optional
        Default False.
    shared_memory : bool, optional
        Zenoh's shared-memory transport between processes on one host (default: Zenoh's,
        enabled in zenoh 1.x).
    config_file : str or Path, optional
        Zenoh configuration file (JSON5).
    credentials : str or Path, optional
        Credentials directory (:mod:`streamer.bus.security`): the session talks mutual TLS
        only (``tls/`` endpoints; default listen ``tls/127.0.0.1:<free port>``) with the
        certificate of ``identity``; a router also enforces the access-control list of
        :func:`streamer.bus.access_control.access_control` (unless the file sets ``access_control``).
    identity : str, optional
        Role whose certificate the session presents (``fitter``, ``launcher``, ``router``...);
        required with ``credentials``.
    connect_timeout : float, optional
        How long a client keeps trying to reach its router when the session opens [s]
        (default :data:`CLIENT_CONNECT_TIMEOUT`, or the file's ``connect/timeout_ms``).
    """

    mode: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    multicast_scouting: bool | None = None
    shared_memory: bool | None = None
    config_file: str | Path | None = None
    credentials: str | Path | None = None
    identity: str | None = None
    connect_timeout: float | None = None

    def to_dict(self) -> dict:
        """JSON-ready form (for passing to child processes)."""
        return {
            "mode": self.mode,
            "listen": None if self.listen is None else list(self.listen),
            "connect": None if self.connect is None else list(self.connect),
            "multicast_scouting": self.multicast_scouting,
            "shared_memory": self.shared_memory,
            "config_file": None if self.config_file is None else str(self.config_file),
            "credentials": None if self.credentials is None else str(self.credentials),
            "identity": self.identity,
            "connect_timeout": self.connect_timeout,
        }

    @classmethod
    def from_dict(cls, d: dict | None) -> SessionSettings:
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`SessionConfigError`."""
        d = dict(d or {})
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise SessionConfigError(f"session settings: unknown field {sorted(unknown)[0]!r}")
        for name in ("listen", "connect"):
            if d.get(name) is not None:
                d[name] = tuple(d[name])
        return cls(**d)


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port free on ``host`` right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def loopback_endpoint(port: int | None = None, protocol: str = "tcp") -> str:
    """``<protocol>/127.0.0.1:<port>`` (a free port when None)."""
    return f"{protocol}/{LOOPBACK}:{free_port() if port is None else int(port)}"


def _get(config: zenoh.Config, key: str):
    """Value of ``key`` in a Zenoh config (None when unset)."""
    value = config.get_json(key)
    return json.loads(value) if isinstance(value, str) else value


def _set(config: zenoh.Config, key: str, value) -> None:
    config.insert_json5(key, json.dumps(value))


def make_config(settings: SessionSettings | None = None) -> zenoh.Config:
    """Build the :class:`zenoh.Config` of ``settings`` (see :class:`SessionSettings`).

    Raises
    ------
    SessionConfigError
        If the file is unreadable or a value invalid; the message names the file or field.
    """
    s = settings or SessionSettings()
    config = _base_config(s.config_file)
    try:
        mode = s.mode or _get(config, "mode") or "peer"
        if mode not in MODES:
            raise SessionConfigError(f"mode: {mode!r} is not one of {', '.join(MODES)}")
        _set(config, "mode", mode)
        _set_endpoints(config, s, mode)
        _set_transport(config, s, mode)
        if s.credentials is not None:
            _secure(config, s, mode)
    except zenoh.ZError as exc:
        raise SessionConfigError(f"invalid Zenoh setting: {exc}") from exc
    for endpoint in _endpoints(_get(config, "listen/endpoints")):
        if LOOPBACK not in endpoint and "localhost" not in endpoint:
            log.warning("Zenoh listens on %s (not loopback only), as configured", endpoint)
    return config


def _base_config(config_file: str | Path | None) -> zenoh.Config:
    """The Zenoh configuration of ``config_file``, or Zenoh's default without one."""
    if config_file is None:
        return zenoh.Config()
    path = Path(config_file)
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh raises ZError with the parser's message
        raise SessionConfigError(f"{path}: invalid Zenoh configuration: {exc}") from exc


def _set_endpoints(config: zenoh.Config, s: SessionSettings, mode: str) -> None:
    """Where the session listens (loopback only unless told: Zenoh's default would listen on
    every interface), connects, and whether it scouts by multicast (not unless told)."""
    protocol = "tls" if s.credentials is not None else "tcp"
    if s.listen is not None:
        _set(config, "listen/endpoints", list(s.listen))
    elif not isinstance(_get(config, "listen/endpoints"), list):
        # unset in the file: Zenoh's default would listen on every interface
        _set(config, "listen/endpoints", [] if mode == "client" else [loopback_endpoint(protocol=protocol)])
    if s.connect is not None:
        _set(config, "connect/endpoints", list(s.connect))
    if s.multicast_scouting is not None:
        _set(config, "scouting/multicast/enabled", bool(s.multicast_scouting))
    elif _get(config, "scouting/multicast/enabled") is None:
        _set(config, "scouting/multicast/enabled", False)


def _set_transport(config: zenoh.Config, s: SessionSettings, mode: str) -> None:
    """Shared memory, the blocking-send wait, the lease and the client's connect timeout."""
    if s.shared_memory is not None:
        _set(config, "transport/shared_memory/enabled", bool(s.shared_memory))
    # Zenoh's defaults (5 s, 10 s) unless a configuration file changed them
    wait_key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    if _get(config, wait_key) == 5_000_000:
        _set(config, wait_key, int(BLOCK_WAIT_BEFORE_CLOSE * 1e6))  # microseconds
    if _get(config, "transport/link/tx/lease") == 10_000:
        _set(config, "transport/link/tx/lease", int(LEASE * 1e3))  # milliseconds
    if s.connect_timeout is not None:
        _set(config, "connect/timeout_ms", int(s.connect_timeout * 1e3))
    elif mode == "client" and _get(config, "connect/timeout_ms") is None:
        _set(config, "connect/timeout_ms", int(CLIENT_CONNECT_TIMEOUT * 1e3))


def _secure(config: zenoh.Config, s: SessionSettings, mode: str) -> None:
    """Mutual TLS with the identity's certificate, TLS links only, and (router) the ACL."""

    if not s.identity:
        raise SessionConfigError("credentials given without an identity (the role whose certificate to use)")
    if s.credentials is None:  # (called only with credentials)
        raise SessionConfigError("an identity given without the credentials directory")
    try:
        tls = Identity(Path(s.credentials), s.identity).tls(listen=mode != "client")
    except CredentialsError as exc:
        raise SessionConfigError(str(exc)) from None
    for name, value in tls.items():
        _set(config, f"transport/link/tls/{name}", value)
    for what in ("listen", "connect"):
        plain = [e for e in _endpoints(_get(config, f"{what}/endpoints")) if not e.startswith("tls/")]
        if plain:
            raise SessionConfigError(
                f"{what} endpoint {plain[0]!r}: with credentials every link is TLS "
                f"(write tls/{plain[0].split('/', 1)[-1]})"
            )
    _set(config, "transport/link/protocols", ["tls"])
    if mode == "router" and not (_get(config, "access_control") or {}).get("enabled"):
        _set(config, "access_control", access_control())


def _endpoints(value) -> list[str]:
    if isinstance(value, dict):  # per-mode form {"peer": [...], "router": [...]}
        return [e for v in value.values() for e in (v or [])]
    return list(value or [])


def open_session(settings: SessionSettings | None = None) -> zenoh.Session:
    """Open a Zenoh session (see :class:`SessionSettings` for the defaults)."""
    config = make_config(settings)
    session = zenoh.open(config)
    log.info(
        "zenoh session %s open (mode %s, listen %s, connect %s)",
        session.zid(),
        _get(config, "mode"),
        _get(config, "listen/endpoints"),
        _get(config, "connect/endpoints"),
    )
    return session


def open_router(
    listen: Iterable[str] = DEFAULT_ROUTER_LISTEN,
    connect: Iterable[str] = (),
    config_file: str | Path | None = None,
    credentials: str | Path | None = None,
) -> zenoh.Session:
    """Open a Zenoh router in this process (``mode="router"``).

    Parameters
    ----------
    listen : sequence of str
        Endpoints to listen on (default ``tcp/127.0.0.1:7447``).
    connect : sequence of str
        Other routers to connect to (several hosts).
    config_file : path, optional
        Zenoh configuration file; ``listen`` and ``connect`` override its endpoints.
    credentials : path, optional
        Credentials directory: mutual TLS with the ``router`` certificate and the run's
        access-control list (:mod:`streamer.bus.security`).
    """
    return open_session(
        SessionSettings(
            mode="router",
            listen=tuple(listen),
            connect=tuple(connect),
            config_file=config_file,
            credentials=credentials,
            identity="router" if credentials is not None else None,
        )
    )


# ---------------------------------------------------------------------------- liveliness


def declare_alive(session: zenoh.Session, run: str, stage: str):
    """Declare the liveliness token ``ttl/<run>/alive/<stage>`` (undeclare it on exit)."""
    return session.liveliness().declare_token(alive_key(run, stage))


def alive_stages(session: zenoh.Session, run: str, timeout: float = 1.0) -> set[str]:
    """Names of the stages of ``run`` whose liveliness token is present now."""
    stages = set()
    for reply in session.liveliness().get(alive_pattern(run), timeout=timeout):
        if reply.ok is not None:
            stages.add(parse_alive_key(str(reply.ok.key_expr))[1])
    return stages


def watch_alive(session: zenoh.Session, run: str, callback: Callable[[str, bool], None]):
    """Call ``callback(stage, alive)`` whenever a stage of ``run`` appears or goes.

    Stages alive at declaration are reported too.  Returns the liveliness subscriber
    (undeclare it, or declare it through :meth:`Bus.watch_alive`).
    """

    def on_sample(sample) -> None:
        _, stage = parse_alive_key(str(sample.key_expr))
        callback(stage, sample.kind == zenoh.SampleKind.PUT)

    return session.liveliness().declare_subscriber(alive_pattern(run), on_sample, history=True)


# ---------------------------------------------------------------------------- the bus


@dataclass
class Bus:
    """A Zenoh session and everything declared through it, closed together.

    Use as a context manager::

        with Bus.open(SessionSettings(connect=("tcp/127.0.0.1:7447",))) as bus:
            pub = bus.segment_publisher(run, "tdi")
            ...

    On exit, every declared entity is undeclared (most recent first) and the session is
    closed, even on error.
    """

    session: zenoh.Session
    _declared: list = field(default_factory=list)

    @classmethod
    def open(cls, settings: SessionSettings | None = None) -> Bus:
        return cls(open_session(settings))

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def track(self, entity):
        """Undeclare ``entity`` when the bus closes; returns it."""
        self._declared.append(entity)
        return entity

    def segment_publisher(self, run: str, topic: str, cache: int = DEFAULT_CACHE) -> SegmentPublisher:
        return self.track(SegmentPublisher(self.session, run, topic, cache))

    def segment_subscriber(
        self, key_expr: str, callback, *, history: int | None = None, on_miss=None
    ) -> SegmentSubscription:
        return self.track(
            declare_segment_subscriber(self.session, key_expr, callback, history=history, on_miss=on_miss)
        )

    def refetch(
        self, key_expr: str, index: int, header: bytes | None, on_sample, *, on_done=None, sn: int | None = None
    ) -> None:
        """Segment ``index`` of stream ``key_expr`` again from the publishers' caches (:func:`refetch_segment`)."""
        refetch_segment(self.session, key_expr, index, header, on_sample, on_done=on_done, sn=sn)

    def subscriber(self, key_expr: str, callback):
        """A plain subscriber (control messages, errors)."""
        return self.track(self.session.declare_subscriber(key_expr, callback))

    def queryable(self, key_expr: str, callback):
        """A queryable (control commands answered with their verdict); ``callback(query)``
        runs on a Zenoh thread; the query is answered once it is dropped
        (:class:`streamer.bus.transport.ControlReply`)."""
        return self.track(self.session.declare_queryable(key_expr, callback))

    def ask(self, key: str, payload: bytes, *, attachment: bytes, timeout: float) -> Iterator[tuple[bool, bytes]]:
        """Query ``key`` with ``payload``: ``(ok, payload)`` of every reply as it comes (not
        merged: a stage may answer twice, queued then accepted), until every queryable
        reached has finished answering or ``timeout`` seconds have passed."""
        replies = self.session.get(
            key,
            payload=payload,
            attachment=attachment,
            timeout=timeout,
            consolidation=zenoh.ConsolidationMode.NONE,
            target=zenoh.QueryTarget.ALL,
        )
        for reply in replies:
            sample = reply.ok if reply.ok is not None else reply.err
            yield reply.ok is not None, (sample.payload.to_bytes() if sample is not None else b"")

    def declare_alive(self, run: str, stage: str):
        return self.track(declare_alive(self.session, run, stage))

    def alive_stages(self, run: str, timeout: float = 1.0) -> set[str]:
        return alive_stages(self.session, run, timeout)

    def watch_alive(self, run: str, callback):
        return self.track(watch_alive(self.session, run, callback))

    def put_json(self, key: str, obj) -> None:
        """Publish a small JSON message (BLOCK, reliable)."""
        self.session.put(
            key,
            json.dumps(obj, allow_nan=False, default=str).encode(),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def close(self) -> None:
        """Undeclare everything (most recent first), then close the session."""
        while self._declared:
            entity = self._declared.pop()
            try:
                entity.undeclare()
            except Exception as exc:  # keep closing the rest
                log.warning("undeclaring %r failed: %s", entity, exc)
        if not self.session.is_closed():
            self.session.close()
