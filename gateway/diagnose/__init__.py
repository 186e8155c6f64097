"""Offline diagnosis of mismatches between a recording and the nominal model."""
