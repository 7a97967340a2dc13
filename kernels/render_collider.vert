// render_collider.vert: a unit mesh (sphere, capped cylinder, cube or square patch) placed in the
// scene by its model matrix (clothbench/reports/render.py).

uniform mat4 view_projection;
uniform mat4 model;
uniform mat3 normal_matrix;  // inverse transpose of model's 3x3 part

in vec3 position;
in vec3 normal;
out vec3 world;
out vec3 normal_v;

void main()
{
    vec4 w = model * vec4(position, 1.0);
    world = w.xyz;
    normal_v = normal_matrix * normal;
    gl_Position = view_projection * w;
}
