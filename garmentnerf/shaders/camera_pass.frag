#version 330 core
// Target 0 (RGBA32F): (b1, b2, camera-space z, face index + 1), cleared to 0 = background.
//   Perspective-correct barycentrics of corners 1 and 2; the face index is exact as a float for
//   fewer than 2^24 faces (checked on the Python side). One target instead of separate float and
//   integer ones halves the bytes llvmpipe clears, shades and reads back.
// Target 1 (RG32F, only with HAS_UV): interpolated texture coordinates.

in vec2 v_bary12;
in float v_depth;
#if HAS_UV
in vec2 v_uv;
layout(location = 1) out vec2 out_uv;
#endif

layout(location = 0) out vec4 out_bary_depth_face;

void main() {
    out_bary_depth_face = vec4(v_bary12, v_depth, float(gl_PrimitiveID + 1));
#if HAS_UV
    out_uv = v_uv;
#endif
}
