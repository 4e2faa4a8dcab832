#version 330 core
// Ground-truth shaded pass (garmentnerf.data.render_gt): indexed triangles with per-vertex
// smooth normals computed on the CPU each frame. World-space position and normal go to the
// fragment shader, which lights them. The clip position is computed exactly as in
// camera_pass.vert (same expression), so coverage matches the CameraPass G-buffer bit for bit.

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip (conventions.Camera.gl_projection)

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;

out vec3 v_world;
out vec3 v_normal;

void main() {
    vec4 p_cam = u_view * vec4(in_position, 1.0);
    v_world = in_position;
    v_normal = in_normal;
    gl_Position = u_proj * p_cam;
}
