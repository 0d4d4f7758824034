"""Command-line options spelled once for every command (the one convention for output folders)."""
from __future__ import annotations

import argparse
import sys


def output_option(p, old: str, help: str, **kw) -> None:
    """``-o/--output DIR``, the one spelling of an output folder; ``old`` stays as a deprecated alias
    (same destination; :class:`DeprecatedAlias` says so when it is used)."""
    p.add_argument("-o", "--output", metavar="DIR", dest=old.lstrip("-").replace("-", "_"), help=help, **kw)
    p.add_argument(old, metavar="DIR", dest=old.lstrip("-").replace("-", "_"), action=DeprecatedAlias, **kw,
                   help="deprecated spelling of -o/--output")


class DeprecatedAlias(argparse.Action):
    """Stores the value like the new option and says once, on stderr, which spelling replaces it."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        print(f"{parser.prog}: {option_string} is deprecated; use -o/--output", file=sys.stderr)
