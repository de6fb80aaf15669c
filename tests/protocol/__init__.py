"""Tests of protocol/ (see docs/architecture.md)."""
