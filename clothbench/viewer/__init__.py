"""`clothbench view`: the cloth live in a window, the backend and the grid switched by key
while it runs, with the hierarchical profiler. keys.py names the keys, session.py is the
simulation behind the window (switching, the shadow run), profiler.py the stage tree,
camera.py the trackball, draw.py and overlay_text.py what is drawn, app.py the window."""

from clothbench.viewer.app import ViewReport, ViewSettings, view

__all__ = ["ViewReport", "ViewSettings", "view"]
