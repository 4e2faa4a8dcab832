#version 330 core
// Box-filter resolve: output pixel (c, r) is the plain mean of the u_factor x u_factor block of
// source texels starting at (c, r) * u_factor (row 0 = image row 0 in both), in a fixed order.
// Drawn with fullscreen_triangle.vert (a full-screen triangle).

uniform sampler2D u_source;
uniform int u_factor;

layout(location = 0) out vec4 out_mean;

void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * u_factor;
    vec4 sum = vec4(0.0);
    for (int dy = 0; dy < u_factor; ++dy) {
        for (int dx = 0; dx < u_factor; ++dx) {
            sum += texelFetch(u_source, base + ivec2(dx, dy), 0);
        }
    }
    out_mean = sum / float(u_factor * u_factor);
}
