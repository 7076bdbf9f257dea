"""Per-channel estimation on raw I/Q: the batched RACKF/CKF/UKF prefilters, PB-KF-UTC, the
inner (scalar) loop and its closed-loop simulator."""
