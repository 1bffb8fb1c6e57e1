"""Makes usd-core find LightFuse's codeless USD schemas (schemas/usd) in every test: the
plugin path must be set before `pxr` is first imported."""
import os
import pathlib

_SCHEMAS = str(pathlib.Path(__file__).resolve().parents[2] / "schemas" / "usd")
_paths = [p for p in os.environ.get("PXR_PLUGINPATH_NAME", "").split(os.pathsep) if p]
if _SCHEMAS not in _paths:
    os.environ["PXR_PLUGINPATH_NAME"] = os.pathsep.join([_SCHEMAS, *_paths])
