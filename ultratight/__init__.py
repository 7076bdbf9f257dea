"""ultratight: a software GPS L1 C/A receiver with ultra-tight (deep) SINS coupling.

Sub-packages, in import order (a package imports only those to its left):

    ins  <-  signals  <-  fusion  <-  receiver

``ultratight.constants`` and ``ultratight.errors`` sit below all of them.
"""

__version__ = "0.1.0"
