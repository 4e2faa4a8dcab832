#version 330 core
// Supersampling resolve of garmentnerf.data.render_gt: output pixel (c, r) is the u_factor x
// u_factor block of source texels starting at (c, r) * u_factor (row 0 = image row 0 in both).
// Output: rgb = plain mean of the block (box filter, fixed summation order: deterministic),
// a = n_body + 256 n_layer0 + 65536 n_layer1, the numbers of subsamples whose label (source alpha) is
// body / garment layer 0 / garment layer 1 (exact in float32: at most 16 x 16 subsamples each).

uniform sampler2D u_source;  // RGBA32F: rgb and label (0 background, 1 body, 2 + k garment layer k)
uniform int u_factor;

layout(location = 0) out vec4 out_color_counts;

void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * u_factor;
    vec3 sum = vec3(0.0);
    float n_body = 0.0;
    float n_inner = 0.0;
    float n_outer = 0.0;
    for (int dy = 0; dy < u_factor; ++dy) {
        for (int dx = 0; dx < u_factor; ++dx) {
            vec4 t = texelFetch(u_source, base + ivec2(dx, dy), 0);
            sum += t.rgb;
            n_body += (t.a > 0.5 && t.a < 1.5) ? 1.0 : 0.0;
            n_inner += (t.a > 1.5 && t.a < 2.5) ? 1.0 : 0.0;
            n_outer += (t.a > 2.5) ? 1.0 : 0.0;
        }
    }
    out_color_counts = vec4(sum / float(u_factor * u_factor), n_body + 256.0 * n_inner + 65536.0 * n_outer);
}
