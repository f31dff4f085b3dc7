"""Interactive viewer: ``python -m nvs.viewer ckpt_path=...`` serves a page on 127.0.0.1 that re-renders a source image
as the camera moves.

controls.py  pose controls per data format (object azimuth/elevation, scene forward/sideways) -> T_tgt_src
images.py    upload decoding (centre crop + resize) and the PNGs the page shows
session.py   the loaded model: encodes each source once, renders poses in the fast mode
build.py     config -> session (checkpoint, camera, controls, gallery), shared with nvs.render_video / nvs.export_ply
paths.py     camera paths for videos (orbit, forward, custom keyframes) inside the trained range
video.py     frames (view | depth) of a path -> MP4 and GIF
cloud.py     a view's predicted depth -> coloured points (PLY via nvs.report.pointcloud)
server.py    the aiohttp app (page, JSON API) and its loopback-only start-up
process.py   the viewer in a child process, for the tools and tests that drive it over HTTP
load.py      ``python -m nvs.viewer.load``: views per second through the HTTP endpoint
screenshot.py ``python -m nvs.viewer.screenshot``: the README's picture of the page
"""
