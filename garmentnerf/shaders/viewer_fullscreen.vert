#version 330 core
// One triangle covering the viewport (gl_VertexID 0..2, no vertex buffer). v_uv is (0, 0) at the
// bottom-left of the viewport and (1, 1) at its top-right.

out vec2 v_uv;

void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    v_uv = p;
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
