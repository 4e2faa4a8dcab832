#version 330 core
// The posed body's depth for the bake's body test (garmentnerf.bake.draw.BakeDrawer).
uniform mat4 u_world_to_camera;
uniform mat4 u_projection;

in vec3 in_position;

void main() {
    gl_Position = u_projection * (u_world_to_camera * vec4(in_position, 1.0));
}
