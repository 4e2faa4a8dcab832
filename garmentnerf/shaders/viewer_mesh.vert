#version 330 core
// Previewer body mesh (garmentnerf.viewer.renderables.BodyMesh): positions and smooth normals per vertex,
// uploaded when the shown frame changes. u_proj is the *display* projection
// (renderables.display_projection: Camera.gl_projection with its y flip undone), so image row 0 lands
// at the top of the window and front faces keep GL's default counter-clockwise winding.

uniform mat4 u_view;  // world -> OpenCV camera (x_cam = R x + t)
uniform mat4 u_proj;  // OpenCV camera -> GL clip, y up on screen

layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;

out vec3 v_world;
out vec3 v_normal;

void main() {
    v_world = in_position;
    v_normal = in_normal;
    gl_Position = u_proj * (u_view * vec4(in_position, 1.0));
}
