"""``shakerlab import``: turn recordings from other systems into a shakerlab run file."""


def register(subparsers) -> None:
    """Add ``import`` to the ``shakerlab`` parser (implemented with the recording format)."""
