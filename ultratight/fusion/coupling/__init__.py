"""INS/GNSS coupling models: the 15-state loose and 17-state tight integration filters, the
rate converters between the 1 kHz channels and the INS, and FADS/GNSS/INS air-data fusion."""
