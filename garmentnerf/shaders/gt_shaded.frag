#version 330 core
// Ground-truth shading (garmentnerf.data.render_gt), all in world space, lights fixed in the world
// so every camera sees the same radiance apart from the small specular term:
//   c = base * side * (hemi_ambient(n) + sum_k I_k max(n.L_k, 0)) + side * k_s * I_0 max(n.h_0, 0)^p
// Two-sided: on a back-facing triangle (the inside of the garment, seen at the hem) the normal is
// flipped toward the viewer and the color scaled by u_inside (side = u_inside, else 1). The
// Python side sets glFrontFace so that gl_FrontFacing is true for faces wound counter-clockwise
// as seen from outside (the project's winding) under the y-flipping projection.
// Output: rgb and the label (0 background, 1 body, 2 + k garment layer k) in alpha.

#define NUM_LIGHTS 2

uniform vec3 u_base_color;
uniform float u_label;
uniform float u_inside;           // color factor of back faces
uniform vec3 u_camera_center;     // world
uniform vec3 u_light_dir[NUM_LIGHTS];        // unit vectors toward the lights (world)
uniform float u_light_intensity[NUM_LIGHTS];
uniform vec3 u_sky;               // hemispheric ambient from +Z
uniform vec3 u_ground;            // hemispheric ambient from -Z
uniform float u_specular;         // strength of the key light's Blinn-Phong lobe
uniform float u_shininess;

in vec3 v_world;
in vec3 v_normal;

layout(location = 0) out vec4 out_color_label;

void main() {
    vec3 n = v_normal;
    float len = length(n);
    n = len > 1e-12 ? n / len : vec3(0.0, 0.0, 1.0);
    float side = 1.0;
    if (!gl_FrontFacing) {
        n = -n;
        side = u_inside;
    }
    vec3 view = normalize(u_camera_center - v_world);
    vec3 light = mix(u_ground, u_sky, 0.5 * n.z + 0.5);
    for (int k = 0; k < NUM_LIGHTS; ++k) {
        light += u_light_intensity[k] * max(dot(n, u_light_dir[k]), 0.0);
    }
    vec3 h = normalize(u_light_dir[0] + view);
    float spec = dot(n, u_light_dir[0]) > 0.0 ? pow(max(dot(n, h), 0.0), u_shininess) : 0.0;
    vec3 c = side * (u_base_color * light + u_specular * u_light_intensity[0] * spec);
    out_color_label = vec4(clamp(c, 0.0, 1.0), u_label);
}
