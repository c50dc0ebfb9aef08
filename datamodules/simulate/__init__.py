"""A physically grounded simulator of MMAUD-like multi-sensor recordings."""
