"""Recorded IF: sample formats and packed layouts, IF file reading and writing, JSON sidecars
and SigMF metadata, and the checks that a recording matches its declaration."""
