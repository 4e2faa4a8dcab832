#version 330 core
// Camera-view pass over NON-indexed triangles (vertex 3 f + k is corner k of face f), so
// gl_VertexID % 3 names the corner and gl_PrimitiveID the face. HAS_UV is #defined (0 or 1) by
// the loader (garmentnerf.gl.shaders).

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip (conventions.Camera.gl_projection)

layout(location = 0) in vec3 in_position;
#if HAS_UV
layout(location = 1) in vec2 in_uv;
out vec2 v_uv;
#endif

out vec2 v_bary12;  // barycentrics of corners 1 and 2; corner 0's is 1 - b1 - b2
out float v_depth;

void main() {
    vec4 p_cam = u_view * vec4(in_position, 1.0);
    int corner = gl_VertexID % 3;
    v_bary12 = vec2(corner == 1 ? 1.0 : 0.0, corner == 2 ? 1.0 : 0.0);
    v_depth = p_cam.z;  // affine over the triangle, so perspective-correct interpolation is exact
#if HAS_UV
    v_uv = in_uv;
#endif
    gl_Position = u_proj * p_cam;
}
