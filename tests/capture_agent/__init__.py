"""Tests of capture_agent/ (see docs/architecture.md)."""
