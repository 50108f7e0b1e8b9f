"""Synthetic demo scenes (analytic ray caster) for tests and quick runs."""
from retinexgs.demo.synthetic import DemoCamera, cast_rays, demo_cameras, make_demo_scene

__all__ = ["DemoCamera", "cast_rays", "demo_cameras", "make_demo_scene"]
