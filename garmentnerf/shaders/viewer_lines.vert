#version 330 core
// Previewer line segments (garmentnerf.viewer.renderables.LineSet): world positions and a colour per
// vertex, drawn as GL_LINES with the display projection (see viewer_mesh.vert).

uniform mat4 u_view;  // world -> OpenCV camera
uniform mat4 u_proj;  // OpenCV camera -> GL clip, y up on screen

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_color;

out vec3 v_color;

void main() {
    v_color = in_color;
    gl_Position = u_proj * (u_view * vec4(in_position, 1.0));
}
