"""The OpenGL passes (moderngl), each owning its GL objects on the context it is given.

- :mod:`~garmentnerf.gl.context`: creating the (headless EGL or window) context; ``current``.
- :mod:`~garmentnerf.gl.resources`: what every pass does with its GL objects (targets kept per
  size, one release).
- :mod:`~garmentnerf.gl.mesh_arrays`: meshes as numpy arrays of checked shapes and indices.
- :mod:`~garmentnerf.gl.shaders`: loading the GLSL of ``garmentnerf/shaders/``.
- :mod:`~garmentnerf.gl.uv_raster`: per-vertex attributes baked into UV-space maps (the info maps;
  read by :mod:`garmentnerf.model.uv_maps`).
- :mod:`~garmentnerf.gl.dilation`: gutter filling of UV-space maps.
- :mod:`~garmentnerf.gl.camera_pass`: the camera-view G-buffer (depth, face, barycentrics, UV) and
  per-pixel depth ranges.
- :mod:`~garmentnerf.gl.shell_raster`: the distance range of a closed shell along every pixel ray.
"""
