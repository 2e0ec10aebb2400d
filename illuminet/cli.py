"""The ``illuminet`` command line: global options, then one subcommand per module ``commands/*.py``.

Each command module in this package defines ``register(subparsers)``, which adds its parser and sets
``func`` (called with the parsed ``args`` and the validated :class:`Config`, returning an exit
code). Adding a command is adding a module name to :data:`COMMAND_MODULES`.

Errors: every mistake or failure a user can meet is an
:class:`~illuminet.runtime.errors.IllumiNetError`; :func:`main` catches it at the top and prints one
line (``illuminet: MESSAGE``) with its exit status (2 usage/configuration, 1 run-time failure).
``--log-level debug`` prints the traceback too. docs/runtime.md ("Errors") lists the classes.
"""

from __future__ import annotations

import argparse
import difflib
import errno
import importlib
import logging
import os
import sys
import traceback

from illuminet import __version__
from illuminet.runtime.config import Config, ConfigError, apply_overrides, load
from illuminet.runtime.errors import IllumiNetError

# The runtime must not phone home: DepthAI sends telemetry unless told not to, and uploads a camera's
# firmware crash dump to Luxonis unless DEPTHAI_CRASHDUMP=0 (libdepthaicore's own message says so).
os.environ.setdefault("DEPTHAI_TELEMETRY", "0")
os.environ.setdefault("DEPTHAI_CRASHDUMP", "0")
os.environ.setdefault("DEPTHAI_DISABLE_CRASHDUMP_COLLECTION", "1")

#: command modules of this package, in the order --help lists them
COMMAND_MODULES: list[str] = [
    "run",  # run, replay, record
    "demo",  # the pipeline on the built-in default session, to a video
    "bench",  # benchmarks
    "doctor",  # what hardware/drivers are found
    "calibrate",  # calibrate board|capture|intrinsics|stereo|photometric
    "datagen",  # training data of the learned transfer (one process or sharded on Ray)
    "train",  # train an object bundle (the learned transfer)
    "bundle",  # a bundle of any mesh with PRT, no training
    "eval",  # evaluation report
    "relight",  # one RGB-D image -> placed object + radiance
    "config",  # print the effective configuration
]

log = logging.getLogger("illuminet")


class _Parser(argparse.ArgumentParser):
    """argparse, with the fix named when a flag's value starts with '-' (``--exposure -5,100``:
    argparse reads ``-5,100`` as another flag and says only that the value is missing)."""

    def error(self, message: str):
        if message.endswith("expected one argument"):
            message += "; if the value starts with '-', join it to the flag with '=' (e.g. --exposure=-5,100)"
        super().error(message)

    def parse_args(self, args=None, namespace=None):
        """An unknown option of a command (``illuminet demo --fames 3``) is that command's error, with
        the option it is close to: argparse reported it with the top-level usage (``illuminet [-h] ...
        COMMAND ...``), which lists none of the command's options."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            parser = self
            while True:  # down to the (sub)command that was chosen: calibrate board, ...
                subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
                chosen = getattr(ns, subs[0].dest, None) if subs else None
                if chosen not in (subs[0].choices if subs else {}):
                    break
                parser = subs[0].choices[chosen]
            known = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
            hints = []
            for extra in extras:
                flag = extra.split("=", 1)[0]
                close = difflib.get_close_matches(flag, known, n=1) if flag.startswith("-") else []
                if close:
                    hints.append(f"{flag}: did you mean {close[0]}?")
            hint = f" ({'; '.join(hints)})" if hints else f"; `{parser.prog} --help` lists the options"
            parser.error(f"unrecognized arguments: {' '.join(extras)}{hint}")
        return ns


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="illuminet",
        description="IllumiNet-edge: light a virtual object by the real room it is placed in.",
    )
    parser.add_argument("--version", action="version", version=f"illuminet {__version__}")
    parser.add_argument(
        "--config",
        "-c",
        metavar="TOML",
        help="configuration file (default: ./config.toml when present, else built-in defaults)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one configuration key (TOML value syntax); repeatable",
    )
    parser.add_argument("--log-level", choices=("debug", "info", "warning", "error"), help="overrides [logging] level")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    after = _WithGlobalOptions(sub, _global_options_after())
    for name in COMMAND_MODULES:
        importlib.import_module(f"illuminet.commands.{name}").register(after)
    return parser


def _global_options_after() -> argparse.ArgumentParser:
    """The global options once more, for after the command (``illuminet demo --set a.b=1``: where
    people type them): their own names in the namespace, merged by :func:`resolve_config` (the
    options after the command win; every ``--set`` counts)."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("global options (also accepted before the command)")
    g.add_argument(
        "--config", "-c", dest="config_after", metavar="TOML", default=argparse.SUPPRESS, help="configuration file"
    )
    g.add_argument(
        "--set",
        dest="overrides_after",
        action="append",
        metavar="SECTION.KEY=VALUE",
        default=argparse.SUPPRESS,
        help="override one configuration key; repeatable",
    )
    g.add_argument(
        "--log-level",
        dest="log_level_after",
        choices=("debug", "info", "warning", "error"),
        default=argparse.SUPPRESS,
        help="overrides [logging] level",
    )
    return p


class _WithGlobalOptions:
    """The subparsers action, giving every command's parser the global options as a parent."""

    def __init__(self, sub, parent: argparse.ArgumentParser) -> None:
        self._sub, self._parent = sub, parent

    def add_parser(self, name, **kwargs):
        kwargs["parents"] = [*kwargs.get("parents", []), self._parent]
        return self._sub.add_parser(name, **kwargs)

    def __getattr__(self, attr):
        return getattr(self._sub, attr)


def _merge_global_options(args: argparse.Namespace) -> argparse.Namespace:
    """Fold the global options given after the command into the ones given before it (once: the
    ``*_after`` names are removed)."""
    after = {k: vars(args).pop(k) for k in ("config_after", "overrides_after", "log_level_after") if k in vars(args)}
    if after.get("config_after") is not None:
        args.config = after["config_after"]
    args.overrides = list(args.overrides) + list(after.get("overrides_after") or [])
    if after.get("log_level_after") is not None:
        args.log_level = after["log_level_after"]
    return args


def resolve_config(args: argparse.Namespace) -> Config:
    """Config file (explicit, or ./config.toml when present) + --set overrides + flag overrides."""
    args = _merge_global_options(args)
    path = args.config
    implicit = path is None and os.path.isfile("config.toml")
    if implicit:
        path = "config.toml"
    try:
        cfg = load(path)
    except ConfigError as e:
        if not implicit:
            raise
        # the user may not know it was read at all (another tool's config.toml in this folder)
        raise ConfigError(
            f"{e} (./config.toml is read when no --config is given: correct it, pass --config FILE, "
            "or run illuminet from another folder)"
        ) from None
    overrides = list(args.overrides)
    if args.log_level:
        overrides.append(("logging", "level", args.log_level))
    return apply_overrides(cfg, overrides)


def report_error(e: IllumiNetError, *, debug: bool) -> int:
    """Print ``e`` as one line on stderr (after its traceback when ``debug``); return its exit status."""
    if debug:
        traceback.print_exception(e, file=sys.stderr)
    prefix = "configuration error: " if isinstance(e, ConfigError) else ""
    print(f"illuminet: {prefix}{e.one_line()}", file=sys.stderr)
    return e.exit_code


def _name_too_long(e: OSError, *, debug: bool) -> int:
    """A path the system refuses as too long (a name over 255 bytes, a path over 4096): one line naming
    it, exit 2. Every path option met it first in an existence check (pathlib's ``exists`` raises it)."""
    if debug:
        traceback.print_exception(e, file=sys.stderr)
    print(
        f"illuminet: {e.filename}: the path is too long for this system ({e.strerror}); expected file and "
        "folder names of at most 255 bytes: give a shorter path",
        file=sys.stderr,
    )
    return 2


def _not_sparse_fallback(record: logging.LogRecord) -> bool:
    return "unable to use sparse matrix" not in record.getMessage()


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 done, 1 run-time failure, 2 usage/configuration)."""
    from illuminet.runtime.stream.loop import remember_early_interrupt

    remember_early_interrupt()  # a Ctrl-C during start-up stops the run even if a library swallows it
    parser = build_parser()
    args = _merge_global_options(parser.parse_args(argv))
    # --log-level debug shows tracebacks even when the configuration itself is the mistake
    debug = args.log_level == "debug"
    try:
        cfg = resolve_config(args)
    except ConfigError as e:
        if getattr(args.func, "__module__", "") != "illuminet.commands.doctor":
            return report_error(e, debug=debug)
        # the doctor still diagnoses the machine: a broken config.toml is one of its findings, not a
        # reason to refuse (the checks then use the built-in defaults)
        args.config_error, cfg = e.one_line(), None
    except OSError as e:
        if e.errno != errno.ENAMETOOLONG:
            raise
        return _name_too_long(e, debug=debug)
    level = getattr(logging, (cfg.logging.level if cfg is not None else args.log_level or "info").upper())
    logging.basicConfig(level=level, format="%(asctime)s %(levelname).1s %(name)s: %(message)s")
    if level > logging.DEBUG:
        # JAX probes for a TPU on every machine and logs "Unable to initialize backend 'tpu': ...
        # libtpu.so" at INFO: it says only that JAX runs on the CPU, as this project's JAX does
        logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
        # without scipy trimesh logs a traceback with "unable to use sparse matrix, falling back!" and
        # then computes the same normals without it: not a failure, so not shown as one
        logging.getLogger("trimesh.util").addFilter(_not_sparse_fallback)
    try:
        return int(args.func(args, cfg) or 0)
    except IllumiNetError as e:
        return report_error(e, debug=debug or level <= logging.DEBUG)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `illuminet config | head`: the reader left; nothing to report
        # (before OSError, its base class: the clause below re-raised it as a traceback)
        try:
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (the interpreter flushes stdout at exit)
        except OSError:
            pass
        return 0
    except OSError as e:
        if e.errno != errno.ENAMETOOLONG:
            raise
        return _name_too_long(e, debug=debug or level <= logging.DEBUG)
