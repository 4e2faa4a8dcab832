#version 330 core
// A full-screen triangle without buffers (the supersampling resolves of garmentnerf.data.render_gt
// and garmentnerf.gl.body_layer_pass).
void main() {
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
