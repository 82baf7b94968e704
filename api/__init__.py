"""REST API (FastAPI) and operator dashboard; ``create_app`` lives in :mod:`api.app`."""
