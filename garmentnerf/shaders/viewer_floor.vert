#version 330 core
// Previewer floor: one square on the plane z = 0 centred on u_center, made from gl_VertexID
// (triangle strip of 4 vertices, no vertex buffer).

uniform mat4 u_view;
uniform mat4 u_proj;
uniform vec2 u_center;
uniform float u_half_size;

out vec3 v_world;

void main() {
    vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1)) * 2.0 - 1.0;
    v_world = vec3(u_center + corner * u_half_size, 0.0);
    gl_Position = u_proj * (u_view * vec4(v_world, 1.0));
}
