#version 330 core
// Target 0 (RGBA32F): perspective-correct barycentrics of the face's 3 corners + camera-space z.
// Target 1 (RG32F): interpolated UV.
// Target 2 (R32I): face index + 1 (cleared to 0 = background).

in vec3 v_bary;
in float v_depth;
in vec2 v_uv;

layout(location = 0) out vec4 out_bary_depth;
layout(location = 1) out vec2 out_uv;
layout(location = 2) out int out_face;

void main() {
    out_bary_depth = vec4(v_bary, v_depth);
    out_uv = v_uv;
    out_face = gl_PrimitiveID + 1;
}
