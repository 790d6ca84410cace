"""``python -m rgbd_calib.cli``: the ``rgbd-calib`` command."""

from .commands import app

if __name__ == "__main__":  # pool workers re-import the main module: run only in the parent
    app()
