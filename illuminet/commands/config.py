"""``illuminet config``: print the effective configuration (file + overrides) as TOML."""

from __future__ import annotations

import argparse


def register(sub) -> None:
    p = sub.add_parser(
        "config",
        help="print the effective configuration as TOML",
        description="Print the configuration after the file and --set overrides are applied.",
    )
    p.add_argument(
        "--pipeline",
        action="store_true",
        help="print the stage chain this configuration builds, with each stage's declared "
        "requires / optional / provides, instead of the TOML",
    )
    p.set_defaults(func=run)


def _toml_string(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped, everything else as is.

    (``json.dumps`` is not TOML: it writes characters beyond U+FFFF as surrogate pairs, which TOML
    refuses, and leaves DEL unescaped.)
    """
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def run(args: argparse.Namespace, cfg) -> int:
    if getattr(args, "pipeline", False):
        from illuminet.pipeline import build_stages, chain_diagram

        print(chain_diagram(build_stages(cfg)))
        return 0
    print(f"# effective configuration (from {cfg.origin!r})")
    for section, values in cfg.items():
        print(f"\n[{section}]")
        for key, value in values.items():
            print(f"{key} = {_toml_value(value)}")
    return 0
