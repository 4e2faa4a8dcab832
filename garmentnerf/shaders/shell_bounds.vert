#version 330 core
// Ray bounds of an inflated body shell (garmentnerf.model.samplers_culled.ShellRaster).
// Non-indexed triangles: every corner carries its (already inflated) world position. No depth
// test and no culling: the fragment shader writes the distance along the pixel-centre ray and
// MIN blending keeps the nearest and the farthest crossing of any face.

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip (conventions.Camera.gl_projection)

layout(location = 0) in vec3 in_position;

out vec3 v_cam;  // camera-space position: |v_cam| is the distance along the unit ray

void main() {
    vec4 p_cam = u_view * vec4(in_position, 1.0);
    v_cam = p_cam.xyz;  // affine over the triangle: perspective-correct interpolation is exact
    gl_Position = u_proj * p_cam;
}
