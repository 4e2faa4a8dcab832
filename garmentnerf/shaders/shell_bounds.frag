#version 330 core
// One RG32F target blended with MIN (no depth test), cleared to a huge value:
//   r = distance of the nearest crossing of any shell face along the pixel-centre ray,
//   g = minus the distance of the farthest crossing.
// Near and far of every face (entering or leaving alike) keep the bounds right where the
// inflated shell folds over itself (armpits, between the legs); a camera inside the shell is
// detected on the Python side (the ray then starts at 0).

in vec3 v_cam;

layout(location = 0) out vec2 out_bounds;

void main() {
    float t = length(v_cam);
    out_bounds = vec2(t, -t);
}
