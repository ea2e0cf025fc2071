"""Gait planning of a legged robot on perceived terrain (Zhao et al. 2020, section 3.3): step
length, step height, body height and pitch adapted to a stairs model (docs/stairs_gait.md)."""
