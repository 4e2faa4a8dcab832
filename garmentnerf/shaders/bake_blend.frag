#version 330 core
// Blends the baked views a camera draws (garmentnerf.bake.draw.BakeDrawer) and, in mode 0, composes the
// garment with the palette.
//
// u_slot_s_j: layer j of the s-th nearest view as drawn from this camera (bake_view.frag); u_weight[s]
// its angle weight. Where several views cover a pixel their layers are averaged with those weights,
// renormalised over the views that cover it: a = sum_s w_s a_s / sum_s w_s [covered_s], likewise every
// attribute.
//
// Mode 0 (the previewer): the garment premultiplied by its visibility, (a c_G, a), with
//     c_G = clamp(r * sum_i w_i (p_i + o_i), 0, 1)
// over the garment colours i: the hybrid composition of garmentnerf.model.palette.compose with a body
// weight of 0 (garmentnerf.bake.views.maps_from_layers). Blended (ONE, ONE_MINUS_SRC_ALPHA) over the
// rasterised body it is exactly compose()'s image. Mode 1: the blended layer u_layer, unchanged (read
// back by the benchmark, which composes with compose() itself).

#ifndef LAYERS
#define LAYERS 3
#endif
#ifndef SLOTS
#define SLOTS 2
#endif
#define MAX_GARMENT_COLORS 3

uniform sampler2D u_slot[SLOTS * LAYERS];
uniform float u_weight[SLOTS];
uniform vec2 u_target_size;
uniform vec2 u_origin;
uniform int u_mode;
uniform int u_layer;
uniform vec3 u_palette[MAX_GARMENT_COLORS];

layout(location = 0) out vec4 out_color;

// GLSL 3.30 indexes sampler arrays with constants only, so the sum over slots and layers is spelled out.
#define SLOT_LAYER(s, j) texture(u_slot[(s) * LAYERS + (j)], uv)
#if LAYERS > 2
#define ADD_LAYER_2(s) layers[2] += w * SLOT_LAYER(s, 2);
#else
#define ADD_LAYER_2(s)
#endif
#if LAYERS > 3
#define ADD_LAYER_3(s) layers[3] += w * SLOT_LAYER(s, 3);
#else
#define ADD_LAYER_3(s)
#endif
#if LAYERS > 4
#define ADD_LAYER_4(s) layers[4] += w * SLOT_LAYER(s, 4);
#else
#define ADD_LAYER_4(s)
#endif
#define ADD_SLOT(s) w = u_weight[s] * SLOT_LAYER(s, 1).a; total += w; layers[0] += w * SLOT_LAYER(s, 0); layers[1] += w * SLOT_LAYER(s, 1); ADD_LAYER_2(s) ADD_LAYER_3(s) ADD_LAYER_4(s)

void main() {
    vec2 uv = (gl_FragCoord.xy - u_origin) / u_target_size;
    vec4 layers[LAYERS];
    for (int j = 0; j < LAYERS; ++j) {
        layers[j] = vec4(0.0);
    }
    float total = 0.0;
    float w;
    ADD_SLOT(0)
#if SLOTS > 1
    ADD_SLOT(1)
#endif
#if SLOTS > 2
    ADD_SLOT(2)
#endif
    if (total <= 0.0) {
        discard;
    }
    for (int j = 0; j < LAYERS; ++j) {
        layers[j] /= total;
    }
    if (u_mode == 1) {
        vec4 value = vec4(0.0);
        for (int j = 0; j < LAYERS; ++j) {
            if (j == u_layer) {
                value = layers[j];
            }
        }
        out_color = value;
        return;
    }
    vec3 base = vec3(0.0);
    for (int i = 0; i < LAYERS - 2; ++i) {
        base += layers[1][i] * (u_palette[i] + layers[2 + i].rgb);
    }
    float a = clamp(layers[0].a, 0.0, 1.0);
    vec3 garment = clamp(layers[0].rgb * base, 0.0, 1.0);
    out_color = vec4(a * garment, a);
}
