"""Sub-commands contributed by ``rig`` (see shakerlab.cli)."""


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
