"""A simulated TMP-origami shaker rig whose instruments speak real protocols over real transports."""
