#version 330 core
// The body layer (garmentnerf.gl.body_layer_pass): the posed body over NON-indexed triangles
// (vertex 3 f + k is corner k of face f, as in camera_pass.vert), with its vertex normal and atlas UV.

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip (conventions.Camera.gl_projection)

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(location = 2) in vec2 in_uv;

out vec3 v_normal;  // world space, interpolated perspective-correctly as the camera pass's barycentrics
out vec2 v_uv;

void main() {
    v_normal = in_normal;
    v_uv = in_uv;
    gl_Position = u_proj * (u_view * vec4(in_position, 1.0));
}
