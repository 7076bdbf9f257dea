"""The scalar receiver: tracking to observables, LNAV decoding, PVT, built from the dsp stages."""
