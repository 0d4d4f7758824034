"""Sub-commands contributed by ``recon`` (see shakerlab.cli)."""


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
