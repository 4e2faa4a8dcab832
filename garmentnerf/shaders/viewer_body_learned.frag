#version 330 core
// The previewer's body in the run's learned appearance: see viewer_body_learned.vert. Opaque, depth tested
// in the scene pass; u_tint is the body's palette colour p_B.

uniform sampler2D u_albedo;
uniform vec3 u_tint;

in vec3 v_irradiance;
in vec2 v_uv;

layout(location = 0) out vec4 out_color;

void main() {
    out_color = vec4(clamp(u_tint * texture(u_albedo, v_uv).rgb * v_irradiance, 0.0, 1.0), 1.0);
}
