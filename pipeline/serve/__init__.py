"""`relight serve`: a live light-editing session in the browser over a baked cache (docs/SERVE.md).

Modules by concept: `rig` (lights and their switches), `attributes` (USD attribute names <-> light
fields, checked), `placement` (pixel -> surface point -> light transform, new lights), `files` (the
paths clients may name), `session` (the rig, undo, save/load, `Session.frames()`), `stream` (the
render thread feeding viewers), `display` (view, exposure, sRGB, PNG/EXR bytes), `app` (the
Starlette HTTP and WebSocket API), `server` (uvicorn), `page.html` (the page).
"""
