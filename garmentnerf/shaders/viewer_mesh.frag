#version 330 core
// Previewer shading: a studio rig that moves with the camera (key from the upper left of the view,
// a weaker fill from the right, a rim from behind), a world-fixed hemispheric ambient (sky from +Z)
// so up stays visibly up, and a small Blinn-Phong lobe of the key light. Light directions arrive in
// world space (the app rotates the camera-space rig every frame). Two-sided: back faces are lit with
// the normal flipped and darkened. Display values, no gamma handling.

#define NUM_LIGHTS 3

uniform vec3 u_base_color;
uniform vec3 u_camera_center;
uniform vec3 u_light_dir[NUM_LIGHTS];    // unit vectors toward the lights, world space
uniform float u_light_intensity[NUM_LIGHTS];
uniform vec3 u_sky;
uniform vec3 u_ground;
uniform float u_specular;
uniform float u_shininess;
uniform float u_rim;

in vec3 v_world;
in vec3 v_normal;

layout(location = 0) out vec4 out_color;

void main() {
    vec3 n = v_normal;
    float len = length(n);
    n = len > 1e-12 ? n / len : vec3(0.0, 0.0, 1.0);
    float side = 1.0;
    if (!gl_FrontFacing) {
        n = -n;
        side = 0.6;
    }
    vec3 view = normalize(u_camera_center - v_world);
    vec3 light = mix(u_ground, u_sky, 0.5 * n.z + 0.5);
    for (int k = 0; k < NUM_LIGHTS; ++k) {
        light += u_light_intensity[k] * max(dot(n, u_light_dir[k]), 0.0);
    }
    vec3 h = normalize(u_light_dir[0] + view);
    float spec = dot(n, u_light_dir[0]) > 0.0 ? pow(max(dot(n, h), 0.0), u_shininess) : 0.0;
    float rim = u_rim * pow(1.0 - max(dot(n, view), 0.0), 3.0);
    vec3 c = side * (u_base_color * light + vec3(u_specular * spec + rim));
    out_color = vec4(clamp(c, 0.0, 1.0), 1.0);
}
