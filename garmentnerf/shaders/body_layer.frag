#version 330 core
// The body's learned appearance (garmentnerf.model.body_appearance.BodyAppearance) per subsample:
//     a(uv, n) = A(uv) * max(S(n), 0),  S(n) = sum_k u_shading[k] * n.x^e.x n.y^e.y n.z^e.z
// over the monomials e of monomial_exponents(degree), n the normalised interpolated normal, and A
// the albedo texture read bilinearly, clamped at the edge (grid_sample, align_corners=False,
// border; row 0 of the texture is v = 0). The loader #defines SHADING_TERMS (the number of
// monomials) and SHADING_SUM(n), S written out term by term (garmentnerf.gl.body_layer_pass): on
// llvmpipe a loop over exponents read from a uniform made the whole pass 140 ms against 85 ms
// unrolled (998 x 998 subsamples, degree 4, the CPU shared with two trainings).
// Output (a, 1) over a (0, 0, 0, 0) clear: the resolve's box mean is then a premultiplied by
// coverage, and the coverage.

uniform sampler2D u_albedo;
uniform vec3 u_shading[SHADING_TERMS];

in vec3 v_normal;
in vec2 v_uv;

layout(location = 0) out vec4 out_color;

void main() {
    vec3 n = normalize(v_normal);
    out_color = vec4(texture(u_albedo, v_uv).rgb * max(SHADING_SUM(n), vec3(0.0)), 1.0);
}
