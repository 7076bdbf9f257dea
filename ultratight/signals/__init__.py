"""The GPS L1 C/A signal: codes, navigation message, ephemeris, front end, IF files, generator,
and the correlator-level simulator (corrsim) used by tests and benchmarks."""
