#version 330 core
// Previewer floor: anti-aliased grid lines (minor every u_minor metres, major every metre, the X and Y
// axes tinted), a soft contact shadow under the body, and an alpha that fades out with distance
// from u_center so the floor melts into the background. Blended over the cleared background,
// without depth writes (everything in the scene stands on or above it).

uniform vec3 u_floor_color;
uniform vec3 u_line_color;
uniform vec3 u_axis_x_color;
uniform vec3 u_axis_y_color;
uniform float u_minor;
uniform float u_show_grid;
uniform vec2 u_center;
uniform float u_half_size;
uniform float u_opacity;
uniform vec2 u_shadow_center;
uniform float u_shadow_radius;
uniform float u_shadow_strength;

in vec3 v_world;

layout(location = 0) out vec4 out_color;

// Coverage of the lines at integer coord, faded out where cells shrink below a few pixels (no moire).
float line_coverage(vec2 coord) {
    vec2 width = fwidth(coord);
    vec2 d = abs(fract(coord - 0.5) - 0.5) / max(width, vec2(1e-6));
    float lod = 1.0 - smoothstep(0.12, 0.35, max(width.x, width.y));
    return (1.0 - min(min(d.x, d.y), 1.0)) * lod;
}

float axis_coverage(float coord) {
    return 1.0 - min(abs(coord) / max(fwidth(coord), 1e-6), 1.0);
}

void main() {
    vec2 p = v_world.xy;
    vec3 c = u_floor_color;
    if (u_show_grid > 0.5) {
        c = mix(c, u_line_color, 0.35 * line_coverage(p / u_minor));
        c = mix(c, u_line_color, 0.75 * line_coverage(p));
        c = mix(c, u_axis_x_color, axis_coverage(p.y));
        c = mix(c, u_axis_y_color, axis_coverage(p.x));
    }
    float r = length(p - u_shadow_center) / max(u_shadow_radius, 1e-6);
    c *= 1.0 - u_shadow_strength * exp(-r * r);
    float fade = 1.0 - smoothstep(0.45 * u_half_size, u_half_size, length(p - u_center));
    out_color = vec4(c, u_opacity * fade);
}
