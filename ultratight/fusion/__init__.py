"""Estimation: generic filters, robust/adaptive parts, per-channel I/Q prefilters, rate converters."""
