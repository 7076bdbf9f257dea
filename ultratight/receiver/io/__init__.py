"""Output writers of the receivers: RINEX 3 observations and navigation, NMEA, CSV/KML and the
streamed HDF5 result file."""
