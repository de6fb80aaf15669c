"""Tests of the reconstructor package."""
