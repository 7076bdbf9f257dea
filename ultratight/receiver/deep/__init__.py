"""The double-loop ultra-tight engine (Zhao et al. 2014): compiled 1 kHz epochs, SINS + clock, the
outer loop, start-up and hand-over from the scalar receiver, data-bit sources, method registry,
recorder and the engine's solution files."""
