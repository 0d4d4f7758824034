"""The shakerlab run file (HDF5): format, writer, reader, results (docs/recording-format.md)."""
