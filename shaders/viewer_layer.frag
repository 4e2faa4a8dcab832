#version 330 core
// The neural layer (garmentnerf.viewer.scene_gl.NeuralLayer): an image rendered elsewhere (the
// garment, by a worker thread) composited into the scene by its mask and depth.
//   u_color: premultiplied RGBA, image rows top-first (row 0 = top of the view), any resolution
//            (bilinear upsampling to the viewport);
//   u_depth: camera-space depth z (metres along the optical axis) per pixel of the same image,
//            0 or negative where the image is empty; nearest sampling.
// The fragment's depth is written from u_depth with the viewer's projection (near u_near,
// far u_far), so the body occludes the garment and vice versa.

uniform sampler2D u_color;
uniform sampler2D u_depth;
uniform float u_near;
uniform float u_far;
uniform float u_opacity;

in vec2 v_uv;

layout(location = 0) out vec4 out_color;

void main() {
    vec2 uv = vec2(v_uv.x, 1.0 - v_uv.y);
    vec4 c = texture(u_color, uv) * u_opacity;
    float z = texture(u_depth, uv).r;
    if (c.a < 1.0 / 255.0 || z <= 0.0) {
        discard;
    }
    float ndc = (u_far + u_near) / (u_far - u_near) - 2.0 * u_far * u_near / ((u_far - u_near) * z);
    gl_FragDepth = clamp(0.5 * ndc + 0.5, 0.0, 1.0);
    out_color = c;
}
