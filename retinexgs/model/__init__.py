"""Scene models of RetinexGS: the illumination field and the enhancement network."""
