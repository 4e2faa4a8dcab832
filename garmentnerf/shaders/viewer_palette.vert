#version 330 core
// A quad covering u_rect = (x0, y0, x1, y1) in normalised device coordinates (gl_VertexID 0..3 as a
// triangle strip, no vertex buffer). v_uv is (u0, v0) = u_uv_rect.xy at the rect's bottom-left and
// (u1, v1) = u_uv_rect.zw at its top-right: (0, 0, 1, 1) for a whole image, a part of it for a quad
// drawn over only that part of the image (garmentnerf.viewer.palette_layer.filled_quad).

uniform vec4 u_rect;
uniform vec4 u_uv_rect;

out vec2 v_uv;

void main() {
    vec2 p = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1));
    v_uv = mix(u_uv_rect.xy, u_uv_rect.zw, p);
    gl_Position = vec4(mix(u_rect.xy, u_rect.zw, p), 0.0, 1.0);
}
