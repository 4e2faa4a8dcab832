#version 330 core
// UV-space G-buffer, drawn once per atlas and resolution: which UV triangle covers each texel
// centre, and where in it. NON-indexed triangles (vertex 3 f + k is corner k of UV face f), placed
// as in uv_attributes.vert (u -> NDC x, v -> NDC y, so row 0 of the read-back map is v = 0).

layout(location = 0) in vec2 in_uv;

noperspective out vec2 v_bary12;  // barycentrics of corners 1 and 2

void main() {
    int corner = gl_VertexID % 3;
    v_bary12 = vec2(corner == 1 ? 1.0 : 0.0, corner == 2 ? 1.0 : 0.0);
    gl_Position = vec4(in_uv * 2.0 - 1.0, 0.0, 1.0);
}
