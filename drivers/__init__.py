"""Instrument drivers: one module per instrument. Never imports sim_backend."""
