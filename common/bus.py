"""The Service base every racecav process uses to join the bus.

A service is a loop over its inputs: subclasses declare publishers and inputs in ``setup()`` and
do one unit of work per ``step()`` (e.g. wait for the newest scan, publish a command). The base
class owns what every service must do the same way:

- a Zenoh session from the config (explicit endpoints, multicast scouting off, client of the
  car's router);
- a liveliness token ``racecav/<car>/<service>/alive`` and a queryable
  ``racecav/<car>/<service>/status`` answering :class:`ServiceStatus` with the latest outputs,
  both declared after ``setup()`` (alive means set up: inputs subscribed, state loaded);
- inputs that keep only the newest sample (sensor data: a stale scan is worthless) and are
  decoded and validated in the subscriber callback; invalid payloads are counted and logged
  (rate-limited) and never stop the service;
- no input kills or silences a service: an exception escaping a subscriber callback, a query
  handler or ``step()`` is caught, counted in the status (``errors``, ``last_error``), logged
  rate-limited (the first of each kind with its traceback) and the service carries on;
- explicit reconnection: a client that loses its router retries every
  ``bus.reconnect_initial_s`` growing to ``bus.reconnect_max_s`` (zenoh's defaults are 1 s to
  4 s), so commands flow again well within a second of the router listening again;
- command publishers that are express and high priority;
- clean shutdown on SIGINT/SIGTERM (undeclare everything, then close: closing a session with
  live declarations can hang), and systemd's sd_notify READY=1 / WATCHDOG=1 when NOTIFY_SOCKET
  is set.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import socket
import threading
import time
from typing import Any, Callable, Generic, TypeVar

import zenoh

from racecav.common import keys
from racecav.common.codec import DecodeError, decode, encode
from racecav.common.config import BusConfig, Config, ConfigError
from racecav.common.messages import Message, ServiceStatus

M = TypeVar("M", bound=Message)
log = logging.getLogger("racecav.bus")


def zenoh_error(e: BaseException) -> str:
    """One readable line from a zenoh error (without the Rust source locations)."""
    text = " ".join(str(e).split()) or type(e).__name__
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    m = re.search(r'msg: "([^"]*)"', text)
    return (m.group(1) if m else text)[:300]


def zenoh_config(bus: BusConfig, mode: str | None = None, listen: list[str] | None = None,
                 config_file=None) -> zenoh.Config:
    """Build a zenoh.Config from the bus section.

    :param mode: override of bus.mode ("router" for ``racecav router``).
    :param listen: endpoints to listen on (routers); clients listen on nothing.
    :param config_file: a zenoh JSON5 file to start from (access control, TLS, ...).
    :raises ConfigError: a missing/invalid file or an invalid endpoint, in one line.
    """
    try:
        return _zenoh_config(bus, mode, listen, config_file)
    except ConfigError:
        raise
    except Exception as e:
        eps = listen if mode == "router" else bus.connect
        raise ConfigError(f"bus: invalid zenoh setting (endpoints {', '.join(eps or [])}): {zenoh_error(e)}") from None


def _zenoh_config(bus: BusConfig, mode, listen, config_file) -> zenoh.Config:
    path = config_file or bus.zenoh_config
    try:
        conf = zenoh.Config.from_file(str(path)) if path else zenoh.Config()
    except Exception as e:  # missing, unreadable or invalid JSON5: say which file, no traceback
        raise ConfigError(f"zenoh config file {path}: {zenoh_error(e)}") from None
    conf.insert_json5("mode", json.dumps(mode or bus.mode))
    if mode == "router":
        conf.insert_json5("listen/endpoints", json.dumps(listen or []))
        if not path:
            conf.insert_json5("connect/endpoints", "[]")
    else:
        conf.insert_json5("connect/endpoints", json.dumps(bus.connect))
        peer = (mode or bus.mode) == "peer"
        conf.insert_json5("listen/endpoints", json.dumps(bus.listen if peer else []))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    if mode != "router":
        # Reconnect quickly after the router restarts (zenoh: 1 s growing to 4 s by default).
        retry = {"period_init_ms": int(bus.reconnect_initial_s * 1000),
                 "period_max_ms": int(bus.reconnect_max_s * 1000), "period_increase_factor": 1.5}
        conf.insert_json5("connect/retry", json.dumps(retry))
    if bus.user is not None and mode != "router":
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(bus.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(bus.password or ""))
    if bus.tls_root_ca is not None:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(bus.tls_root_ca)))
    if bus.tls_cert is not None and bus.tls_key is not None:
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(bus.tls_cert)))
        conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(bus.tls_key)))
    return conf


def sd_notify(state: str) -> bool:
    """Send a systemd notification (READY=1, WATCHDOG=1, STOPPING=1); no-op outside systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):  # abstract namespace socket
        addr = "\0" + addr[1:]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.connect(addr)
        s.sendall(state.encode())
    return True


class RateLimitedLog:
    """Log at most one line per ``period_s`` per topic, with the number suppressed since."""

    def __init__(self, logger: logging.Logger, period_s: float):
        self._logger, self._period = logger, period_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, topic: str, msg: str, exc_info=None) -> bool:
        """Log ``msg`` unless ``topic`` was logged less than a period ago; True if logged.

        :param exc_info: an exception whose traceback is logged with the first line of a topic.
        """
        topic = re.sub(r"\d+", "#", topic)  # "stale scan 123" and "stale scan 124" are one topic
        if len(self._last) > 1000:  # bounded: topics come from input (names, sources)
            self._last.clear()
            self._suppressed.clear()
        now = time.monotonic()
        last = self._last.get(topic)
        if last is not None and now - last < self._period:
            self._suppressed[topic] = self._suppressed.get(topic, 0) + 1
            return False
        n = self._suppressed.pop(topic, 0)
        self._last[topic] = now
        self._logger.warning("%s%s", msg, f" ({n} more suppressed)" if n else "",
                             exc_info=exc_info if last is None else None)
        return True


class Inbox(Generic[M]):
    """Newest-only input of one message type.

    Decoding happens in Zenoh's callback thread (short, never blocks); the service loop takes
    the newest valid message with :meth:`take`. A message overwritten before it was taken is
    counted as dropped.
    """

    def __init__(self, service: "Service", key: str, cls: type[M]):
        self.key, self.cls, self._service = key, cls, service
        self._cond = threading.Condition()
        self._msg: M | None = None
        self._fresh = False
        self.arrival_ns = 0
        """Monotonic arrival time of the newest message."""

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._service.guard(f"input {self.key}"):
            self._store(self._service._decode(self.key, sample.payload.to_bytes(), self.cls))

    def _store(self, msg: M | None) -> None:
        if msg is None:
            return
        with self._cond:
            if self._fresh:
                self._service.dropped += 1
            self._msg, self._fresh, self.arrival_ns = msg, True, time.monotonic_ns()
            self._cond.notify_all()

    def take(self, timeout: float | None = None) -> M | None:
        """Wait up to ``timeout`` s for a message not yet taken; return it, or None."""
        with self._cond:
            if not self._fresh and not self._cond.wait_for(lambda: self._fresh, timeout):
                return None
            self._fresh = False
            return self._msg

    def latest(self) -> tuple[M | None, int]:
        """The newest message (taken or not) and its monotonic arrival time in ns."""
        with self._cond:
            return self._msg, self.arrival_ns


class Publisher:
    """Typed publisher that counts what it sends and remembers the latest message for status."""

    def __init__(self, service: "Service", key: str, command: bool):
        self.key, self._service = key, service
        opts: dict[str, Any] = {}
        if command:
            # Commands must not queue behind bulk data: express (no batching), high priority.
            opts = dict(express=True, priority=zenoh.Priority.INTERACTIVE_HIGH,
                        congestion_control=zenoh.CongestionControl.DROP)
        self._pub = service.session.declare_publisher(key, **opts)
        self.latest: Message | None = None

    def put(self, msg: Message) -> None:
        self._pub.put(encode(msg))
        self.latest = msg
        self._service.published += 1

    def undeclare(self) -> None:
        self._pub.undeclare()


class Service:
    """Base class of every racecav service. Subclass, override ``setup`` and ``step``, call ``run``.

    :param cfg: the whole configuration (``cfg.bus`` says how to join the bus).
    :param name: service name: the third level of its keys (racecav/<car>/<name>/status).
    :param mode: "router" for the car's router itself; None for the bus config's mode.
    """

    def __init__(self, cfg: Config, name: str, mode: str | None = None, listen: list[str] | None = None,
                 zenoh_config_file=None):
        self.cfg, self.name, self.car = cfg, name, cfg.bus.car
        self._mode, self._listen, self._zenoh_file = mode, listen, zenoh_config_file
        self.log = logging.getLogger(f"racecav.{name}")
        self._rlog = RateLimitedLog(self.log, cfg.bus.status_log_period_s)
        self.stop_event = threading.Event()
        self.received = self.published = self.invalid = self.dropped = self.errors = 0
        self.last_error = ""
        self._started = time.monotonic()
        self._declared: list[Any] = []
        self._publishers: list[Publisher] = []
        self._status_seq = 0
        self.session: zenoh.Session | None = None
        self._config_digest = cfg.digest()

    # --- declarations (call from setup) ---------------------------------------------------

    def topic(self, name: str) -> str:
        return keys.topic(self.car, name)

    def publisher(self, key: str, command: bool = False) -> Publisher:
        """Declare a publisher; ``command=True`` for drive commands (express, high priority)."""
        pub = Publisher(self, key, command)
        self._publishers.append(pub)
        return pub

    def inbox(self, key: str, cls: type[M]) -> Inbox[M]:
        """Declare a newest-only input of message type ``cls`` on ``key``."""
        box: Inbox[M] = Inbox(self, key, cls)
        self._declared.append(self.session.declare_subscriber(key, box._on_sample))
        return box

    def subscribe(self, key: str, cls: type[M] | None, callback: Callable[[Any], None]) -> None:
        """Every-sample input (e.g. e-stop): ``callback(msg)`` for each valid message, or
        ``callback(raw_bytes)`` when ``cls`` is None. Keep the callback short."""

        def on_sample(sample: zenoh.Sample) -> None:
            with self.guard(f"input {key}"):
                data = sample.payload.to_bytes()
                if cls is None:
                    self.received += 1
                    callback(data)
                    return
                msg = self._decode(key, data, cls)
                if msg is not None:
                    callback(msg)

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def watch_alive(self, service: str, callback: Callable[[str, bool], None]) -> None:
        """Follow ``service``'s liveliness token on this car ("*": every service's):
        ``callback(name, True)`` when it appears (or already exists), ``callback(name, False)``
        when it vanishes. A process that dies (kill -9,
        crash) loses its TCP link and the router withdraws its token at once: this is how a
        consumer learns of a dead producer in milliseconds rather than after a timeout."""
        key = keys.alive_key(self.car, service)

        def on_sample(sample: zenoh.Sample) -> None:
            with self.guard(f"liveliness {service}"):
                callback(str(sample.key_expr).split("/")[2], sample.kind != zenoh.SampleKind.DELETE)

        self._declared.append(self.session.liveliness().declare_subscriber(key, on_sample, history=True))

    def queryable(self, leaf: str, handler: Callable[[bytes | None], Message | dict]) -> None:
        """Declare racecav/<car>/<service>/<leaf>; ``handler(payload)`` returns the reply (a
        Message, encoded; or a JSON-able dict). An exception becomes a reply error: a
        ValueError (a bad payload: the handler's validation) counts as ``invalid``, anything
        else as ``errors``."""
        key = keys.service_key(self.car, self.name, leaf)

        def on_query(query: zenoh.Query) -> None:
            try:
                payload = query.payload.to_bytes() if query.payload is not None else None
                out = handler(payload)
                data = encode(out) if isinstance(out, Message) else json.dumps(out).encode()
                query.reply(key, data)
            except ValueError as e:  # a bad payload, refused by the handler
                self._record_error(f"query {leaf}: {e}")  # the cause before the count
                self.invalid += 1
                self._reply_err(query, str(e))
            except Exception as e:  # a bad query must not kill the service
                self._record_error(f"query {leaf}: {type(e).__name__}: {e}", e)
                self.errors += 1
                self._reply_err(query, f"{type(e).__name__}: {e}")

        self._declared.append(self.session.declare_queryable(key, on_query))

    @staticmethod
    def _reply_err(query: zenoh.Query, text: str) -> None:
        try:
            query.reply_err(text[:1000].encode())
        except Exception:  # the querier is gone: nothing left to tell
            pass

    # --- counters ---------------------------------------------------------------------------

    def guard(self, where: str) -> "_Guard":
        """``with self.guard("what"):`` runs a block whose exceptions are counted as ``errors``,
        logged (rate-limited) and swallowed: for callbacks and loop steps, never for set-up."""
        return _Guard(self, where)

    def _decode(self, key: str, data: bytes, cls: type[M]) -> M | None:
        self.received += 1
        try:
            return decode(data, cls, self.cfg.bus.max_payload_bytes)
        except DecodeError as e:
            self._record_error(f"invalid payload on {key}: {e}")
            self.invalid += 1
            return None

    def _record_error(self, text: str, exc: BaseException | None = None) -> None:
        self.last_error = text[:1000]
        self._rlog.warning(text.split(":")[0], self.last_error, exc_info=exc)

    def info(self) -> dict[str, Any]:
        """Service-specific status fields; override to add mode, source, solver stats..."""
        return {}

    def status(self) -> ServiceStatus:
        self._status_seq += 1
        outputs = {p.key: p.latest.model_dump(mode="json") for p in self._publishers if p.latest is not None}
        try:
            info = self.info()
            json.dumps(info)  # must survive encoding: a bad value must not break every status query
        except Exception as e:
            self.errors += 1
            self._record_error(f"status info: {type(e).__name__}: {e}", e)
            info = {"info_error": self.last_error}
        st = ServiceStatus(
            stamp_ns=time.monotonic_ns(), seq=self._status_seq, service=self.name, car=self.car,
            pid=os.getpid(), uptime_s=time.monotonic() - self._started, received=self.received,
            published=self.published, invalid=self.invalid, dropped=self.dropped, errors=self.errors,
            last_error=self.last_error, config_digest=self._config_digest, info=info,
            outputs=outputs)
        try:
            encode(st)  # e.g. an integer beyond 64 bits in info: report that, keep answering
        except ValueError as e:
            self.errors += 1
            self._record_error(f"status: {e}")
            st = st.model_copy(update={"info": {"info_error": str(e)[:500]}, "outputs": {},
                                       "errors": self.errors, "last_error": self.last_error})
        return st

    # --- life cycle -------------------------------------------------------------------------

    def setup(self) -> None:
        """Declare publishers, inputs and extra queryables. Override."""

    def step(self) -> None:
        """One unit of work; must return within about a second (watchdog). Override."""
        self.stop_event.wait(0.1)

    def teardown(self) -> None:
        """Called on stop, before undeclaring (e.g. send a last neutral command). Override."""

    def open(self) -> None:
        """Join the bus and declare everything.

        :raises ConfigError: the session cannot be opened (no router at ``bus.connect``, an
            invalid endpoint, a router endpoint in use): one line naming the endpoints.
        """
        conf = zenoh_config(self.cfg.bus, self._mode, self._listen, self._zenoh_file)
        try:
            self.session = zenoh.open(conf)
        except Exception as e:
            where = (f"listen {', '.join(self._listen or [])}" if self._mode == "router"
                     else f"bus.connect {', '.join(self.cfg.bus.connect)}")
            raise ConfigError(f"{self.name}: cannot join the bus ({where}): {zenoh_error(e)}") from None
        self.setup()
        # status and token last: a service that answers or shows alive is set up (its subscribers
        # declared, its state loaded), so a client acting on either is heard and told the truth
        self.queryable("status", lambda _payload: self.status())
        self._declared.append(self.session.liveliness().declare_token(keys.alive_key(self.car, self.name)))

    def close(self) -> None:
        try:
            self.teardown()
        finally:
            for obj in [*self._publishers, *reversed(self._declared)]:
                try:
                    obj.undeclare()
                except Exception as e:  # already gone; keep closing the rest
                    self.log.debug("undeclare: %s", e)
            self._publishers.clear()
            self._declared.clear()
            if self.session is not None:
                self.session.close()
                self.session = None

    def request_stop(self, *_: Any) -> None:
        self.stop_event.set()

    def run(self) -> int:
        """Open, loop ``step()`` until SIGINT/SIGTERM or ``request_stop()``, then close cleanly."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self.request_stop)
            signal.signal(signal.SIGTERM, self.request_stop)
        watchdog_s = int(os.environ.get("WATCHDOG_USEC", "0")) / 2e6
        try:
            self.open()
        except BaseException:  # a failed setup(): undeclare and close (an open session can hang the exit)
            try:
                self.close()
            except Exception as e:  # the setup error is the one to report
                self.log.debug("close after a failed setup: %s", e)
            raise
        try:
            self.log.info("%s started on car %s", self.name, self.car)
            sd_notify("READY=1")
            last_ping = 0.0
            while not self.stop_event.is_set():
                ok = False
                with self.guard("step"):
                    self.step()
                    ok = True
                if not ok:  # a step that keeps failing must not spin a core
                    self.stop_event.wait(0.01)
                if watchdog_s and time.monotonic() - last_ping >= watchdog_s:
                    sd_notify("WATCHDOG=1")
                    last_ping = time.monotonic()
        finally:
            sd_notify("STOPPING=1")
            self.close()
            self.log.info("%s stopped", self.name)
        return 0


class _Guard:
    """Context manager behind :meth:`Service.guard`."""

    def __init__(self, service: Service, where: str):
        self.service, self.where = service, where

    def __enter__(self) -> None:
        return None

    def __exit__(self, typ, exc, tb) -> bool:
        if exc is None or not isinstance(exc, Exception):
            return False
        # The cause before the count: a status taken in between must not pair them wrongly.
        self.service._record_error(f"{self.where}: {typ.__name__}: {exc}", exc)
        self.service.errors += 1
        return True
