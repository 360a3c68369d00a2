"""The simulated calibration station: a ray-cast scene behind calstation's driver interfaces."""
