#version 330 core
// UV-space attribute rasteriser: every triangle of the UV atlas is drawn at its texture
// coordinates, carrying NUM_TARGETS vec4 attributes per vertex (4 channels per render target).
// NUM_TARGETS is #defined by the loader (garmentnerf.gl.shaders).
//
// u in [0, 1] -> NDC x in [-1, 1] (left to right); v in [0, 1] -> NDC y in [-1, 1]. The
// framebuffer read back row by row therefore has row 0 at v = 0: the layout of GL texture memory,
// and the one that grid_sample reads with grid = 2 * uv - 1 (see gl/uv_raster.py).
// w = 1 everywhere, so interpolation is linear in UV space (no perspective).

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec4 in_attr[NUM_TARGETS];

noperspective out vec4 v_attr[NUM_TARGETS];

void main() {
    for (int i = 0; i < NUM_TARGETS; ++i) {
        v_attr[i] = in_attr[i];
    }
    gl_Position = vec4(in_uv * 2.0 - 1.0, 0.0, 1.0);
}
