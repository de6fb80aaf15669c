"""The file formats the parts of EgoSurg exchange (all TOML but the ZED factory file): node.toml
and rig.toml (with their camera tables and ``[security]``: the agent, the recorder and the
simulator's deploy share them), a camera table, the rig calibration, the ZED conf, evaluation
sets, sites, trajectories and the wand."""
