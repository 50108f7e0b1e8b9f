"""``retinexgs view``: a web viewer (viser) of a trained run. ``camera`` and ``frame`` are torch only and
import no viser; ``server`` needs the optional extra (``pip install "retinexgs[view]"``)."""
