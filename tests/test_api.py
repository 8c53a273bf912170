"""The stable API names of docs/conventions.md §Python API are importable from ``lightplane`` and documented."""

import lightplane


def test_stable_names():
    for name in ("Camera", "LightPlane", "detect_ellipses", "extract_stripe", "circle_poses", "calibrate_plane",
                 "triangulate", "distance_errors"):
        obj = getattr(lightplane, name)
        assert callable(obj), name
        assert obj.__doc__ and len(obj.__doc__) > 40, f"{name} lacks a docstring"
