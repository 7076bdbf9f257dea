"""Signal processing stages: IF block stream, acquisition, correlator bank, tracking loops, data
wipe-off, lock monitor and correlator-level noise bursts."""
