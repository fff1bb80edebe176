"""Tests of librplus_client (python -m unittest)."""
