"""`benchctl console`: a local web page to watch the camera and drive the laser and SLM, in one process that holds
the devices through their drivers. Needs the `console` extra (Starlette, uvicorn, websockets)."""
