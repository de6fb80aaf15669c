"""The wire messages, one module per kind: ``checks`` (errors, the binary prefix, the version
rule, buffer and JSON field checks), ``frame``, ``status`` (agent status and
``decode_published``) and ``control``.

The spec, byte by byte, is one docstring: ``protocol/messages.py``'s, which is also where every
other module imports these names from. Like all of protocol/, this imports only numpy.
"""
