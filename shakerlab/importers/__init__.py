"""Readers of recordings from other systems, one module per format, for ``shakerlab import``.

- ``csv_file``: the shakerlab CSV (header names the channels), read line by line;
- ``lms_mat``: LMS Test.Lab MATLAB exports (scipy.io.loadmat);
- ``tdms``: NI TDMS (npTDMS, optional extra ``formats``);
- ``uff58``: UFF/UNV dataset 58 (pyuff, optional extra ``formats``);
- ``timebase``: the uniform-sampling check every reader's time base goes through;
- ``mapping``: channel -> role mapping (``--map ROLE=CHANNEL[:QUANTITY]`` or a TOML file).

Every reader returns :class:`Signal` objects; every bad input raises UserFacingError naming
the file and the channel, line or sample.
"""
