"""The file formats the parts of EgoSurg exchange (all TOML but the ZED factory file): a camera
table, the rig calibration, the ZED conf, evaluation sets, sites, trajectories and the wand."""
