#version 330 core
// A baked view's garment attributes where its surface is the nearest of that view and not behind the
// body (garmentnerf.bake.draw.BakeDrawer). Writes the view's layers as they are stored
// (garmentnerf.bake.views: layer 0 radiance rgb + the garment's visibility a, layer 1 the garment
// colours' weights, layer 2 + i the offset of garment colour i), with layer 1's fourth channel set to 1:
// the view covers this pixel.
//
// The body test: the body's depth u_body_depth (a depth texture of the drawing camera, NDC depth in
// [0, 1]) is pushed back by u_body_margin metres; the garment is hidden only where the body is further
// in front of it than that (cloth lies within a couple of centimetres of the skin, where the network's
// own w_B decides, and a bake has no w_B).

#ifndef LAYERS
#define LAYERS 3
#endif

uniform sampler2DArray u_layers;  // the view's 8-bit codes (normalised): value = u_low[j] + code * u_span[j]
uniform vec4 u_low[LAYERS];
uniform vec4 u_span[LAYERS];
uniform sampler2D u_body_depth;
uniform vec2 u_target_size;
uniform float u_body_margin;
uniform float u_near;
uniform float u_far;

in vec2 v_uv;
in float v_z;

layout(location = 0) out vec4 out_layer0;
layout(location = 1) out vec4 out_layer1;
#if LAYERS > 2
layout(location = 2) out vec4 out_layer2;
#endif
#if LAYERS > 3
layout(location = 3) out vec4 out_layer3;
#endif
#if LAYERS > 4
layout(location = 4) out vec4 out_layer4;
#endif

float linear_z(float d) {
    float ndc = 2.0 * d - 1.0;
    return 2.0 * u_near * u_far / (u_far + u_near - ndc * (u_far - u_near));
}

void main() {
    float body = texture(u_body_depth, gl_FragCoord.xy / u_target_size).r;
    if (body < 1.0 && v_z > linear_z(body) + u_body_margin) {
        discard;
    }
    out_layer0 = u_low[0] + u_span[0] * texture(u_layers, vec3(v_uv, 0.0));
    out_layer1 = vec4((u_low[1] + u_span[1] * texture(u_layers, vec3(v_uv, 1.0))).rgb, 1.0);
#if LAYERS > 2
    out_layer2 = u_low[2] + u_span[2] * texture(u_layers, vec3(v_uv, 2.0));
#endif
#if LAYERS > 3
    out_layer3 = u_low[3] + u_span[3] * texture(u_layers, vec3(v_uv, 3.0));
#endif
#if LAYERS > 4
    out_layer4 = u_low[4] + u_span[4] * texture(u_layers, vec3(v_uv, 4.0));
#endif
}
