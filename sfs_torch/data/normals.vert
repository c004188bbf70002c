#version 330 core
// sfs_torch.preview: camera-frame normals for pyrender's offscreen renderer (RenderFlags.FLAT).
// pyrender prepends its #defines (NORMAL_LOC, INST_M_LOC, ...) after the #version line.
layout(location = 0) in vec3 position;
layout(location = NORMAL_LOC) in vec3 normal;
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

out vec3 frag_position;
out vec3 frag_normal;

void main()
{
    // The mesh node's pose is the world-to-camera rotation and the camera's pose a pure
    // translation along z, so that M's frame is the camera frame of sfs_torch.rendering.
    gl_Position = P * V * M * inst_m * vec4(position, 1.0);
    frag_position = vec3(M * inst_m * vec4(position, 1.0));
    frag_normal = mat3(M * inst_m) * normal;
}
