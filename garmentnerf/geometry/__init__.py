"""Geometry of sample points against the body surface.

- :mod:`~garmentnerf.geometry.triangles`: pure functions on triangles (closest point, distance in
  a face's frame, reach, pseudo-normals, barycentric interpolation).
- :mod:`~garmentnerf.geometry.projection`: exact closest points on a triangle mesh (a tree of
  faces bounded by oriented boxes, walked by a native kernel on the CPU,
  :mod:`~garmentnerf.geometry.face_bvh`).
- :mod:`~garmentnerf.geometry.projection_dense`: the same queries by brute force in torch (GPU).
- :mod:`~garmentnerf.geometry.body_points`: the paper's body-aware coordinates x^b = [b_o, h] and
  the UV of the closest point.
- :mod:`~garmentnerf.geometry.winding`: inside/outside a closed mesh by generalised winding numbers.
"""
