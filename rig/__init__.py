"""The acquisition controller: protocol, runner, safety supervision, recording."""
