"""Simulation of the signal: the sampled-IF generator (and its streamed and shared-memory forms),
the front end, the correlator-level simulator and the observable-level simulator."""
