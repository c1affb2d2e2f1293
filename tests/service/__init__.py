"""Tests of the service layer (store, sessions, ingest)."""
