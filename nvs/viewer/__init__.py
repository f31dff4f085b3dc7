"""Interactive viewer: ``python -m nvs.viewer ckpt_path=...`` serves a page on 127.0.0.1 that re-renders a source image
as the camera moves.

controls.py  pose controls per data format (object azimuth/elevation, scene forward/sideways) -> T_tgt_src
images.py    upload decoding (centre crop + resize) and the PNGs the page shows
session.py   the loaded model: encodes each source once, renders poses in the fast mode
server.py    the aiohttp app (page, JSON API) and its loopback-only start-up
load.py      ``python -m nvs.viewer.load``: views per second through the HTTP endpoint
"""
