#version 330 core
// The previewer's body in the run's learned appearance (garmentnerf.viewer.renderables.LearnedLook: the body
// the window draws while the neural garment has not arrived). The colour the raster_body composition
// gives the body is
//     c = clamp(p_B * A(uv) * max(S(n), 0), 0, 1),  S(n) = sum_k u_shading[k] * n.x^e.x n.y^e.y n.z^e.z
// with p_B the body's palette colour, A the albedo texture and S the shading polynomial of the unit world
// normal over the monomials e = u_exponents[k] (garmentnerf.body.shading.monomial_exponents). Here
// max(S(n), 0) is evaluated per vertex and interpolated (shaders/body_layer.frag evaluates it per
// subsample): on llvmpipe the per-fragment sum, written out term by term as body_layer.frag does, took
// 1.2 to 2.9 s to compile at its first draw, and a loop over the terms per fragment 0.18 s a draw at
// 960 x 600; per vertex it costs neither, and this body is the first thing the window draws.

#define MAX_TERMS 64

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip, y up on screen (renderables.display_projection)
uniform vec3 u_shading[MAX_TERMS];
uniform ivec3 u_exponents[MAX_TERMS];
uniform int u_terms;

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(location = 2) in vec2 in_uv;

out vec3 v_irradiance;  // max(S(n), 0)
out vec2 v_uv;

void main() {
    float len = length(in_normal);
    vec3 n = len > 1e-12 ? in_normal / len : vec3(0.0, 0.0, 1.0);
    vec3 s = vec3(0.0);
    for (int k = 0; k < u_terms; ++k) {
        ivec3 e = u_exponents[k];
        float m = 1.0;
        for (int i = 0; i < e.x; ++i) {
            m *= n.x;
        }
        for (int i = 0; i < e.y; ++i) {
            m *= n.y;
        }
        for (int i = 0; i < e.z; ++i) {
            m *= n.z;
        }
        s += u_shading[k] * m;
    }
    v_irradiance = max(s, vec3(0.0));
    v_uv = in_uv;
    gl_Position = u_proj * (u_view * vec4(in_position, 1.0));
}
