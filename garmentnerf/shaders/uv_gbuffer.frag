#version 330 core
// Target 0 (RGBA32F): (b1, b2, UV face index + 1, 1); cleared to 0 = no triangle. The face index
// is exact as a float below 2^24 faces (checked on the Python side).

noperspective in vec2 v_bary12;

layout(location = 0) out vec4 out_bary_face;

void main() {
    out_bary_face = vec4(v_bary12, float(gl_PrimitiveID + 1), 1.0);
}
