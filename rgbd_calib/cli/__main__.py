"""``python -m rgbd_calib.cli``: the ``rgbd-calib`` command."""

from .commands import app

app()
