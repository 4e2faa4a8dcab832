#version 330 core
// Depth only (garmentnerf.bake.draw.BakeDrawer's body pass).
void main() {
}
