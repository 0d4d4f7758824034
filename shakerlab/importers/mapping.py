"""Which channel of a file plays which role: ``--map ROLE=CHANNEL[:QUANTITY]`` or a TOML file.

Roles: ``t`` (a time channel), ``force``, and the motion roles ``x_base``, ``x_tip``
(base excitation) or ``x`` (force excitation); for a component test (``--constitutive``) also
``velocity`` (a measured velocity beside x) and ``command`` (an extra input). A motion role may carry its quantity as a
suffix (``x_tip=Time_Laser__X:v``, quantities ``x``/``v``/``a`` or the full words) or in its
name (``v_tip=Time_Laser__X``); without one, the file's own declaration (UFF) or
displacement. The TOML form is a ``[map]`` table of the same ``ROLE = "CHANNEL[:QUANTITY]"``.
"""
from __future__ import annotations

from pathlib import Path

from shakerlab.errors import UserFacingError
from shakerlab.quantities import ALIASES, parse_channel

ROLES = ("t", "force", "x_base", "x_tip", "x", "velocity", "command")
# a component test's extra channels (shakerlab.modes; only with `import --constitutive`)
EXTRA_ROLES = ("velocity", "command")


def parse_entry(text: str, where: str = "--map") -> tuple[str, str, str | None]:
    """(role, channel, quantity or None) of one ``ROLE=CHANNEL[:QUANTITY]``."""
    role, eq, rest = text.partition("=")
    role, rest = role.strip(), rest.strip()
    if not eq or not role or not rest:
        raise UserFacingError(f"{where} {text!r}: expected ROLE=CHANNEL[:QUANTITY], e.g. x_tip=Time_Laser__X:v")
    quantity = None
    channel = rest
    head, colon, tail = rest.rpartition(":")
    if colon and tail.strip().lower() in ALIASES:
        channel, quantity = head.strip(), ALIASES[tail.strip().lower()]
    parsed = parse_channel(role)
    if parsed is not None and parsed[0] != role:        # v_tip=...: the quantity in the role's name
        if quantity is not None and quantity != parsed[1]:
            raise UserFacingError(f"{where} {text!r}: role {role} says {parsed[1]}, the suffix says {quantity}")
        role, quantity = parsed
    if role not in ROLES:
        raise UserFacingError(f"{where} {text!r}: unknown role {role!r}; roles are {', '.join(ROLES)} "
                              f"(motion roles may be written v_tip, a_base, v, ...)")
    if quantity is not None and role in ("t", "force") + EXTRA_ROLES:
        raise UserFacingError(f"{where} {text!r}: role {role} takes no quantity")
    if not channel:
        raise UserFacingError(f"{where} {text!r}: no channel name")
    return role, channel, quantity


def parse(entries: list[str] | None, toml_file: str | Path | None = None) -> dict:
    """{role: (channel, quantity or None)} from --map options and/or a TOML file."""
    out: dict = {}
    items = []
    if toml_file is not None:
        import tomllib  # lazy: only with --map-file

        path = Path(toml_file)
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserFacingError(f"{path}: no such file") from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise UserFacingError(f"{path}: not a readable TOML file ({exc})") from None
        table = doc.get("map")
        unknown = set(doc) - {"map"}
        if not isinstance(table, dict) or unknown:
            raise UserFacingError(f"{path}: expected one [map] table of ROLE = \"CHANNEL[:QUANTITY]\""
                                  + (f" (unknown: {', '.join(sorted(unknown))})" if unknown else ""))
        for role, value in table.items():
            if not isinstance(value, str):
                raise UserFacingError(f"{path}: [map] {role}: expected a string \"CHANNEL[:QUANTITY]\"")
            items.append((f"{role}={value}", f"{path}: [map]"))
    items += [(e, "--map") for e in entries or []]
    for text, where in items:
        role, channel, quantity = parse_entry(text, where)
        if role in out:
            raise UserFacingError(f"{where} {text!r}: role {role} is mapped twice")
        out[role] = (channel, quantity)
    if out:
        motion = [r for r in out if r in ("x_base", "x_tip", "x")]
        if "force" in out and set(motion) != {"x"} or "force" not in out and set(motion) != {"x_base", "x_tip"}:
            raise UserFacingError(f"the channel map gives {', '.join(sorted(out))}: map x_base and x_tip (base "
                                  f"excitation) or force and x (force excitation), and optionally t")
    return out
