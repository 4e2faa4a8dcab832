#version 330 core
// Writes the interpolated attributes to NUM_TARGETS RGBA32F render targets in one draw call.

noperspective in vec4 v_attr[NUM_TARGETS];

layout(location = 0) out vec4 out_attr[NUM_TARGETS];

void main() {
    for (int i = 0; i < NUM_TARGETS; ++i) {
        out_attr[i] = v_attr[i];
    }
}
