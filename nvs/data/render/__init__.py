"""Render real meshes from Debian packages into the two dataset formats (see docs/datasets.md).

`python -m nvs.data.render <chairs|cars|drive|contact> [size=256] [out=...] [seed=0] [max_models=N]
[sequences=N frames=N]`. Importing submodules that render sets PYOPENGL_PLATFORM=egl unless already set.
"""
