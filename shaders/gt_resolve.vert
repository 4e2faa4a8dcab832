#version 330 core
// Full-screen triangle for the supersampling resolve of garmentnerf.data.render_gt (no buffers).
void main() {
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
