#version 330 core
// Camera-view pass over NON-indexed triangles (vertex 3 f + k is corner k of face f), so
// gl_VertexID % 3 names the corner and gl_PrimitiveID the face.

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip (conventions.Camera.gl_projection)

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec2 in_uv;  // left unbound (generic value 0) when the mesh has no UVs

out vec3 v_bary;
out float v_depth;
out vec2 v_uv;

void main() {
    vec4 p_cam = u_view * vec4(in_position, 1.0);
    int corner = gl_VertexID % 3;
    v_bary = vec3(corner == 0 ? 1.0 : 0.0, corner == 1 ? 1.0 : 0.0, corner == 2 ? 1.0 : 0.0);
    v_depth = p_cam.z;  // affine over the triangle, so perspective-correct interpolation is exact
    v_uv = in_uv;
    gl_Position = u_proj * p_cam;
}
