"""The desktop viewer (pyvista/VTK): ``data`` loads an OUT_DIR, ``scene`` builds actors and returns
handles, ``controller`` holds the behaviour as plain methods, ``app`` binds keys/sliders and shows.

Submodules import pyvista lazily; ``import guidewire3d.viewer`` stays light.
"""
