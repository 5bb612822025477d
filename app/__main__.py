"""``python -m app``: start the refocusing web app (same as ``d2f-app``)."""

from app.main import main

if __name__ == "__main__":
    raise SystemExit(main())
