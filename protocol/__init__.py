"""Contracts shared by every part of EgoSurg: camera models, the ZED factory file, wire messages,
control verbs and the session schema.

protocol/ imports none of the other four packages and needs only numpy (and the standard library),
so the edge agent and every offline tool agree on one definition of each format.
"""

__version__ = "0.1.0"
