"""Sub-commands contributed by ``sim_backend`` (see shakerlab.cli)."""


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
