#version 330 core
// sfs_torch.preview: the interpolated vertex normal, flipped where it faces away from the
// camera (as sfs_torch.rendering.render_normals does per ray), encoded as 0.5 n + 0.5.
// The background is cleared to (0.5, 0.5, 0.5, 0) (the zero vector), so that the 4x MSAA
// resolve averages rim samples into a shorter vector of the mean direction, and alpha is
// the covered fraction of the pixel.
uniform vec3 cam_pos;
uniform mat4 P;

in vec3 frag_position;
in vec3 frag_normal;

out vec4 frag_color;

void main()
{
    // P[3][3] is 1 for an orthographic projection, 0 for a perspective one.
    vec3 view = P[3][3] == 1.0 ? vec3(0.0, 0.0, 1.0) : cam_pos - frag_position;
    float len = length(frag_normal);
    if (len < 1e-12) discard;  // opposite vertex normals cancelling on razor-thin parts
    vec3 n = frag_normal / len;
    if (dot(n, view) < 0.0) n = -n;
    frag_color = vec4(0.5 * n + 0.5, 1.0);
}
