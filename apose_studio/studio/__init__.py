"""The browser studio (viser): author assembly files, inspect datasets, captures and registrations.

`serve()` starts it; `app.py` holds the studio and its shared state, one module per panel holds that
panel's widgets and callbacks, `widgets.py` the small shared pieces, `viser_adapter.py` the viser
internals it touches. This package is the only one that imports viser.
"""

from apose_studio.studio.app import Studio, default_workspace, serve
from apose_studio.studio.inspect_panel import EstimateJob
from apose_studio.studio.widgets import MAX_UPLOAD_BYTES, esc

__all__ = ["EstimateJob", "MAX_UPLOAD_BYTES", "Studio", "default_workspace", "esc", "serve"]
