"""The HTTP service: FastAPI app factory (``edgepos.api.app.create_app``), routes, auth, metrics."""
