#version 330 core
// Copies the resolved scene texture to the window (same orientation: texture row 0 is the bottom of
// the window). At equal sizes each fragment samples exactly one texel centre.

uniform sampler2D u_image;

in vec2 v_uv;

layout(location = 0) out vec4 out_color;

void main() {
    out_color = vec4(texture(u_image, v_uv).rgb, 1.0);
}
