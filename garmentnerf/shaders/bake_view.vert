#version 330 core
// One baked view's surface mesh (garmentnerf.bake.draw.BakeDrawer), seen by the drawing camera.
// in_position: world point of the view's surface; in_uv: where it lies on the view's layers (u right,
// v down). v_z is the camera-space z the body test compares.
uniform mat4 u_world_to_camera;
uniform mat4 u_projection;

in vec3 in_position;
in vec2 in_uv;

out vec2 v_uv;
out float v_z;

void main() {
    vec4 cam = u_world_to_camera * vec4(in_position, 1.0);
    v_uv = in_uv;
    v_z = cam.z;
    gl_Position = u_projection * cam;
}
