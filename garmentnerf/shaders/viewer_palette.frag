#version 330 core
// The neural layer's palette composition (garmentnerf.viewer.palette_layer.PaletteLayer): the decomposed
// maps of a neural render, cached as textures, composed with the palette per fragment. This is
// THE SAME formula as garmentnerf.model.palette.compose (tests/render/test_render.py compares them):
//
//     fg = clamp(r * sum_i w_i (p_i + o_i), 0, 1)
//     c  = m * fg + (1 - m) * background
//
// or, with a body layer (u_has_body = 1, the raster_body composition; B = the last palette color),
//
//     m_G = m (1 - w_B),  c_G = clamp(r * sum_{i != B} w_i (p_i + o_i) / (1 - w_B), 0, 1)
//     c   = m_G c_G + (1 - m_G) (clamp(p_B a, 0, 1) + (1 - alpha_b) background)
//
// Both are written premultiplied, (P, A) with c = P + (1 - A) background.
// The layer outputs premultiplied (m * fg, m); blended with (ONE, ONE_MINUS_SRC_ALPHA) over the
// scene that is exactly c with the scene as the background. With u_opaque = 1 it outputs c over
// u_background itself (opaque), as compose() does with that background.
//
// u_maps (sampler2DArray, RGBA32F, rows top-first like every image of the package):
//   layer 0: radiance r (rgb; a grey radiance is uploaded to all three) and mask m (a)
//   layer 1: blend weights w_0..w_3
//   layer 2 + i: offset o_i (rgb) of palette color i
// u_body (sampler2D, RGBA32F, with u_has_body; drawn by garmentnerf.gl.body_layer_pass at the size
//   the layer is shown at, rows as u_maps): the rasterised body's color a premultiplied by its
//   coverage (rgb), and the coverage alpha_b (a)
// The maps fill the part u_map_extent (w / W, h / H) of u_maps and u_depth (the textures grow and are
// kept while frames of a clip differ in size by a few pixels); a map coordinate is clamped half a
// texel inside it, which samples exactly as clamp-to-edge on textures of the maps' own size.
// Changing a color only changes u_palette: recoloring never re-runs the network.
//
// Modes (u_mode): 0 neural, 1 ground truth (u_gt), 2 difference |neural over u_background - gt| x
// u_diff_gain, 3 maps (u_map: 0 mask, 1 blend weights as colors, 2 radiance).
// Depth (u_use_depth = 1): the fragment's depth comes from u_depth (camera-space z, 0 = nothing),
// pulled u_depth_bias metres towards the camera so the network's body surface wins over the
// rasterised body where they coincide; empty pixels go just in front of the far plane (behind
// everything rasterised, in front of the cleared background).

#define MAX_PALETTE 4

uniform sampler2DArray u_maps;
uniform sampler2D u_gt;
uniform sampler2D u_depth;
uniform sampler2D u_body;
uniform vec3 u_palette[MAX_PALETTE];
uniform int u_palette_size;
uniform int u_has_body;
uniform vec3 u_background;
uniform int u_opaque;
uniform int u_mode;
uniform int u_map;
uniform float u_diff_gain;
uniform float u_opacity;
uniform int u_use_depth;
uniform float u_depth_bias;
uniform float u_near;
uniform float u_far;
uniform vec2 u_map_extent;
uniform vec2 u_map_half_texel;

in vec2 v_uv;

layout(location = 0) out vec4 out_color;

const vec3 MAP_COLORS[MAX_PALETTE] = vec3[](vec3(1.0, 0.25, 0.2), vec3(0.2, 0.55, 1.0),
                                             vec3(0.3, 0.9, 0.3), vec3(0.95, 0.85, 0.2));

// uv over the shown image -> the coordinate of u_maps and u_depth (see u_map_extent above).
vec2 map_uv(vec2 uv) {
    return clamp(uv * u_map_extent, u_map_half_texel, u_map_extent - u_map_half_texel);
}

// The character premultiplied by its coverage (returned in alpha): c = result + (1 - alpha) background.
vec3 premultiplied(vec2 uv, out float alpha) {
    vec2 muv = map_uv(uv);
    vec4 rm = texture(u_maps, vec3(muv, 0.0));
    vec4 w = texture(u_maps, vec3(muv, 1.0));
    int garment_colors = u_has_body == 1 ? u_palette_size - 1 : u_palette_size;
    vec3 base = vec3(0.0);
    for (int i = 0; i < MAX_PALETTE; ++i) {
        if (i >= garment_colors) {
            break;
        }
        vec3 o = texture(u_maps, vec3(muv, 2.0 + float(i))).rgb;
        base += w[i] * (u_palette[i] + o);
    }
    if (u_has_body == 0) {
        alpha = rm.a;
        return rm.a * clamp(rm.rgb * base, 0.0, 1.0);
    }
    float share = 1.0 - w[u_palette_size - 1];
    float visible = rm.a * share;
    vec3 garment = clamp(rm.rgb * base / max(share, 1e-6), 0.0, 1.0);
    vec4 body = texture(u_body, uv);
    vec3 body_color = clamp(u_palette[u_palette_size - 1] * body.rgb, 0.0, 1.0);
    alpha = visible + (1.0 - visible) * body.a;
    return visible * garment + (1.0 - visible) * body_color;
}

float ndc_depth(float z) {
    float ndc = (u_far + u_near) / (u_far - u_near) - 2.0 * u_far * u_near / ((u_far - u_near) * z);
    return clamp(0.5 * ndc + 0.5, 0.0, 1.0);
}

void main() {
    vec2 uv = vec2(v_uv.x, 1.0 - v_uv.y);
    float m;
    vec4 result;
    if (u_mode == 1) {
        result = vec4(texture(u_gt, uv).rgb, 1.0);
    } else if (u_mode == 2) {
        vec3 fg = premultiplied(uv, m);
        vec3 c = fg + (1.0 - m) * u_background;
        result = vec4(clamp(abs(c - texture(u_gt, uv).rgb) * u_diff_gain, 0.0, 1.0), 1.0);
    } else if (u_mode == 3) {
        vec4 rm = texture(u_maps, vec3(map_uv(uv), 0.0));
        vec3 c;
        if (u_map == 0) {
            c = vec3(rm.a);
        } else if (u_map == 1) {
            vec4 w = texture(u_maps, vec3(map_uv(uv), 1.0));
            c = vec3(0.0);
            for (int i = 0; i < MAX_PALETTE; ++i) {
                if (i >= u_palette_size) {
                    break;
                }
                c += w[i] * MAP_COLORS[i];
            }
        } else {
            c = clamp(rm.rgb, 0.0, 1.0);
        }
        result = vec4(c, 1.0);
    } else {
        vec3 fg = premultiplied(uv, m);
        result = u_opaque == 1 ? vec4(fg + (1.0 - m) * u_background, 1.0) : vec4(fg, m);
    }
    result *= u_opacity;
    if (u_use_depth == 1) {
        float z = texture(u_depth, map_uv(uv)).r;
        gl_FragDepth = z > 0.0 ? ndc_depth(max(z - u_depth_bias, u_near)) : 0.99999;
    } else {
        gl_FragDepth = gl_FragCoord.z;
    }
    out_color = result;
}
