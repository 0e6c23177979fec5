"""The ``daemon.zenoh`` section: settings, the Zenoh session configuration, the security rule.

``daemon.zenoh`` (absent: no Zenoh) puts the daemon on a Zenoh network (docs/zenoh.md)::

    daemon:
      zenoh:
        prefix: jtc/lab/arm1          # default: jtc/<hostname>/<controller name>
        mode: peer                    # or client (through a router)
        connect: [tcp/192.168.1.10:7447]
        listen: [tcp/127.0.0.1:7447]  # default: none
        config: /etc/jtc-hw/zenoh.json5   # optional Zenoh configuration file, passed as is
        multicast_scouting: false     # discovery by multicast: off unless set here or in config
        token: "at least sixteen characters"  # required: commands carry it (below)

The Zenoh configuration is the file (if any) with this section's keys applied on top; where
neither says, our defaults apply: no listen endpoint (a Zenoh peer's own is every interface), no
multicast scouting, and the session lease :data:`LEASE_MS` / :data:`KEEP_ALIVE`
(docs/zenoh.md, "Configuration").

Two rules, both checked at load (so ``jtc-hw check`` says them too; docs/zenoh.md, "Security"):
``token`` is required, at least :data:`MIN_TOKEN_LENGTH` characters, and every query that
commands the robot carries it (``jtc_hw.daemon.transports.zenoh_iface``): loopback is no
protection on a machine with other users. A listen endpoint that is not loopback needs TLS (a
``tls/`` or ``quic/`` locator with a listen certificate and key) or authentication
(``transport.auth.usrpwd`` or ``pubkey``) in the configuration file. Reading a configuration
file needs the ``eclipse-zenoh`` package (its parser is the reference for its JSON5); a section
without one is checked without it.
"""

from __future__ import annotations

import ipaddress
import json
import multiprocessing
import os
import re
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from ..errors import ConfigurationError
from ..hardware import ParamKind, ParamSpec, param_table

__all__ = [
    "INSTALL_HINT",
    "KEEP_ALIVE",
    "LEASE_MS",
    "MIN_TOKEN_LENGTH",
    "MODES",
    "ZENOH_PARAMETERS",
    "ZenohSettings",
    "default_prefix",
    "endpoint_is_loopback",
    "import_zenoh",
    "is_loopback",
    "session_config",
    "zenoh_settings",
]

INSTALL_HINT: Final = "pip install 'jtc_hw[zenoh]'"
MODES: Final = ("peer", "client")
LEASE_MS: Final = 1000
"""Zenoh session lease the daemon announces (Zenoh's default: 10 s): a peer that hears
nothing from the daemon for this long (its machine powered off, its cable pulled) closes the
session, and the daemon's liveliness token disappears. A daemon that dies with its machine
still up is noticed at once: its TCP connections are closed by the kernel."""
KEEP_ALIVE: Final = 4
"""Keep-alive messages per lease (Zenoh's default), so the lease survives a lost one."""

MIN_TOKEN_LENGTH: Final = 16
"""Shortest ``daemon.zenoh.token``, and ``daemon.tcp.token`` (:mod:`.settings` imports it)."""
TOKEN_HINT: Final = "generate one with: python -c 'import secrets; print(secrets.token_hex(16))'"

_KEY_CHUNK = re.compile(r"[^/*$?#]+")

ZENOH_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("prefix", ParamKind.STRING, None,
              "key expression under which the daemon appears (default: "
              "jtc/<hostname>/<controller name>)", nullable=True),
    ParamSpec("mode", ParamKind.STRING, None,
              "Zenoh session mode: peer, or client of a router (default: the configuration "
              "file's, else peer)", nullable=True, choices=MODES),
    ParamSpec("connect", ParamKind.STRINGS, (),
              "Zenoh endpoints to connect to (a router, a peer), e.g. tcp/10.0.0.2:7447"),
    ParamSpec("listen", ParamKind.STRINGS, None,
              "Zenoh endpoints to listen on (default: the configuration file's, else none); "
              "a non-loopback one needs TLS or authentication in config", nullable=True),
    ParamSpec("config", ParamKind.STRING, None,
              "Zenoh configuration file (JSON5), passed through: TLS, authentication, access "
              "control", nullable=True),
    ParamSpec("multicast_scouting", ParamKind.BOOL, False,
              "discover peers by UDP multicast (off: only connect/listen endpoints)"),
    ParamSpec("token", ParamKind.STRING, None,
              f"shared secret every commanding query carries in its attachment (required, at "
              f"least {MIN_TOKEN_LENGTH} characters)", nullable=True),
)
"""``daemon.zenoh.*``."""


@dataclass(frozen=True)
class ZenohSettings:
    """``daemon.zenoh``: the daemon's Zenoh interface (``jtc_hw.daemon.transports.zenoh_iface``);
    one field per row of :data:`ZENOH_PARAMETERS` (``config`` an absolute path here)."""

    prefix: str | None = None
    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] | None = None
    config: str | None = None
    multicast_scouting: bool = False
    token: str = field(default="", repr=False)

    def resolved_prefix(self, controller: str) -> str:
        """The prefix in effect for a daemon of controller ``controller``."""
        return self.prefix if self.prefix is not None else default_prefix(controller)


def default_prefix(controller: str) -> str:
    """``jtc/<hostname>/<controller>``, with characters a key expression cannot hold in a
    chunk (``/ * $ ? #``) replaced by ``_``."""
    host = socket.gethostname().split(".")[0] or "localhost"
    return "/".join(("jtc", *(re.sub(r"[/*$?#\s]", "_", c) for c in (host, controller))))


def check_prefix(prefix: str, path: str = "daemon.zenoh.prefix") -> str:
    """A prefix as a concrete key expression: chunks separated by ``/``, none empty, no
    wildcard or reserved character.

    Raises:
        ConfigurationError: names the offending chunk.
    """
    if not prefix or prefix.startswith("/") or prefix.endswith("/"):
        raise ConfigurationError(
            f"{prefix!r} is not a key expression: give chunks separated by '/', without a "
            "leading or trailing '/' (e.g. jtc/lab/arm1)", path, prefix)
    for chunk in prefix.split("/"):
        if not _KEY_CHUNK.fullmatch(chunk):
            raise ConfigurationError(
                f"{prefix!r}: chunk {chunk!r} is empty or holds one of * $ ? # (wildcards "
                "are for subscribers; a daemon's prefix names one robot)", path, prefix)
    return prefix


def check_token(token: object) -> str:
    """``daemon.zenoh.token``: present, a string of at least :data:`MIN_TOKEN_LENGTH`.

    Raises:
        ConfigurationError: missing or too short; the message says how to make one and never
            echoes the value.
    """
    if token is None or token == "":
        raise ConfigurationError(
            "is required: without it anyone who reaches the Zenoh network (on loopback: every "
            "local user) could command the robot. Set daemon.zenoh.token and "
            f"give it to the operators (--zenoh-token-file, $JTC_HW_ZENOH_TOKEN); {TOKEN_HINT}",
            "daemon.zenoh.token", None)
    if not isinstance(token, str) or len(token) < MIN_TOKEN_LENGTH:
        raise ConfigurationError(
            f"must be at least {MIN_TOKEN_LENGTH} characters long, got "
            f"{len(token) if isinstance(token, str) else type(token).__name__}; {TOKEN_HINT}",
            "daemon.zenoh.token", None)  # never echo a secret
    return token


LOOP_PROCESS: Final = "jtc-hw-loop"
"""``jtc_hw.daemon.loop.cycle.LOOP_PROCESS_NAME``, the loop process's ``multiprocessing`` name
(not imported: this module is imported by the robot file's loader, the loop's too)."""


def zenoh_settings(values: Mapping[str, Any], base_dir: str) -> ZenohSettings:
    """Settings of a validated ``daemon.zenoh`` mapping, checked against the security rule.

    In the loop process the configuration file is not read again: reading it loads
    eclipse-zenoh, whose native library starts a thread, and the loop process must have none
    (``loop_main``); the daemon's API process checked the same file before starting it.

    Raises:
        ConfigurationError: no ``token`` or a short one; a bad prefix, a missing
            configuration file, no endpoint at all, or a non-loopback listen endpoint without
            TLS or authentication (the message says what to set); ``eclipse-zenoh`` missing
            when a configuration file must be read.
    """
    token = check_token(values.get("token"))
    prefix = values["prefix"]
    if prefix is not None:
        check_prefix(prefix)
    config = values["config"]
    if config is not None:
        if not config.strip():
            raise ConfigurationError("is empty; give a file, or remove the key",
                                     "daemon.zenoh.config", config)
        config = os.path.normpath(os.path.join(base_dir, os.path.expanduser(config)))
        if not os.path.isfile(config):
            raise ConfigurationError(f"{config} is not a file", "daemon.zenoh.config", config)
    listen = values["listen"]
    settings = ZenohSettings(
        prefix=prefix,
        mode=values["mode"],
        connect=tuple(values["connect"]),
        listen=None if listen is None else tuple(listen),
        config=config,
        multicast_scouting=values["multicast_scouting"],
        token=token,
    )
    for index, endpoint in enumerate((*settings.connect, *(settings.listen or ()))):
        if "/" not in endpoint:
            raise ConfigurationError(
                f"{endpoint!r} is not a Zenoh endpoint: write <protocol>/<address>:<port>, "
                "e.g. tcp/127.0.0.1:7447", "daemon.zenoh.connect" if index < len(
                    settings.connect) else "daemon.zenoh.listen", endpoint)
    if settings.config is None or multiprocessing.current_process().name != LOOP_PROCESS:
        check_security(settings)
    return settings


# -- the session configuration ------------------------------------------------------------------


def _json(config: Any, key: str) -> Any:
    return json.loads(config.get_json(key))


def import_zenoh() -> Any:
    """The ``zenoh`` module (imported on first use: the loop process never loads it).

    Raises:
        ConfigurationError: ``eclipse-zenoh`` is missing; the message says what to install.
    """
    try:
        import zenoh  # the optional extra (jtc_hw[zenoh])
    except ImportError:
        raise ConfigurationError(
            f"needs the eclipse-zenoh package: {INSTALL_HINT}, or remove daemon.zenoh",
            "daemon.zenoh",
        ) from None
    return zenoh


def session_config(settings: ZenohSettings) -> Any:
    """The ``zenoh.Config`` of the daemon's session (module docstring: what comes from where).

    Raises:
        ConfigurationError: ``eclipse-zenoh`` is missing, or the configuration file cannot be
            read as a Zenoh configuration.
    """
    zenoh = import_zenoh()
    default = zenoh.Config()
    if settings.config is not None:
        try:
            config = zenoh.Config.from_file(settings.config)
        except Exception as exc:  # zenoh raises its own ZError with the parser's message
            raise ConfigurationError(
                f"{settings.config} is not a valid Zenoh configuration: {exc}",
                "daemon.zenoh.config",
                settings.config,
            ) from None
    else:
        config = zenoh.Config()
    if settings.mode is not None or _json(config, "mode") is None:
        config.insert_json5("mode", json.dumps(settings.mode or "peer"))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.listen is not None:
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    elif _json(config, "listen/endpoints") == _json(default, "listen/endpoints"):
        # Zenoh's default for a peer is tcp/[::]:0, every interface: never by default.
        config.insert_json5("listen/endpoints", "[]")
    if settings.multicast_scouting:
        config.insert_json5("scouting/multicast/enabled", "true")
    elif _json(config, "scouting/multicast/enabled") is None:
        config.insert_json5("scouting/multicast/enabled", "false")
    if _json(config, "transport/link/tx/lease") == _json(default, "transport/link/tx/lease"):
        config.insert_json5("transport/link/tx/lease", str(LEASE_MS))
        config.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVE))
    return config


# -- security -----------------------------------------------------------------------------------


def endpoint_is_loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``tcp/127.0.0.1:7447``, ``tls/[::1]:0#iface=lo``) can only be
    reached from this machine: a loopback address, ``localhost``, or a Unix socket. Never
    raises: anything unreadable counts as reachable from elsewhere."""
    protocol, _, rest = endpoint.partition("/")
    if protocol.startswith("unixsock"):
        return True
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    return is_loopback(host.strip("[]"))


def is_loopback(host: str) -> bool:
    """Whether ``host`` is ``localhost`` or a loopback IP address (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _listen_endpoints(settings: ZenohSettings) -> tuple[list[str], Any]:
    """The listen endpoints in effect, and the parsed file (``None`` without one)."""
    if settings.config is None:
        return list(settings.listen or ()), None
    config = session_config(settings)
    endpoints = _json(config, "listen/endpoints")
    if isinstance(endpoints, dict):  # per mode (Zenoh's own layout)
        mode = _json(config, "mode") or "peer"
        endpoints = endpoints.get(mode) or []
    return [str(e) for e in endpoints or ()], config


def _secured(endpoint: str, config: Any) -> bool:
    if config is None:
        return False
    auth = _json(config, "transport/auth")
    usrpwd = auth.get("usrpwd") or {}
    pubkey = auth.get("pubkey") or {}
    if (usrpwd.get("user") and usrpwd.get("password")) or usrpwd.get("dictionary_file"):
        return True
    if any(pubkey.get(k) for k in ("private_key_pem", "private_key_file")):
        return True
    tls = _json(config, "transport/link/tls")
    return endpoint.split("/", 1)[0] in ("tls", "quic") and bool(
        tls.get("listen_certificate") and tls.get("listen_private_key"))


def check_security(settings: ZenohSettings) -> None:
    """The security rule (module docstring), and that the daemon can reach someone.

    Raises:
        ConfigurationError: a non-loopback listen endpoint without TLS or authentication;
            no endpoint and no scouting (the daemon would reach nobody).
    """
    endpoints, config = _listen_endpoints(settings)
    for endpoint in endpoints:
        if endpoint_is_loopback(endpoint) or _secured(endpoint, config):
            continue
        raise ConfigurationError(
            f"{endpoint} is reachable from other machines and the Zenoh configuration sets "
            "neither TLS nor authentication: anyone on the network could command the robot. "
            "Either listen on a tls/ endpoint with transport.link.tls.listen_certificate and "
            "listen_private_key, or set transport.auth.usrpwd (user, password or "
            "dictionary_file), in the file named by daemon.zenoh.config (docs/zenoh.md has "
            "examples); or listen on 127.0.0.1 only",
            "daemon.zenoh.listen",
            endpoint,
        )
    connect = settings.connect
    if config is not None and not connect:
        connect = tuple(_json(config, "connect/endpoints") or ())
    if not endpoints and not connect and not settings.multicast_scouting and not (
        config is not None and _json(config, "scouting/multicast/enabled")
    ):
        raise ConfigurationError(
            "no connect or listen endpoint and multicast scouting off: the daemon would reach "
            "nobody; set connect (a router or peer, e.g. [tcp/10.0.0.2:7447]) or listen "
            "(e.g. [tcp/127.0.0.1:7447])",
            "daemon.zenoh",
        )
