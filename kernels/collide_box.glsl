// collide_box.glsl: the oriented boxes (docs/semantics.md, "Box").
// Included by the host into verlet_cloth_step.glsl only when the program handles boxes.
// Every result is a `precise` temporary, so strict mode rounds exactly where the reference does.

#ifdef GENERIC
uniform int num_boxes;
uniform vec4 boxes[4 * MAX_COLLIDERS];  // (centre, 0), (axis i, half extent i) for i = 0, 1, 2
#define BOX_COUNT num_boxes
#else
const vec4 boxes[4 * BOX_COUNT] = BOXES_VALUE;  // as above, four rows each
#endif

// a particle strictly inside the box (centre c, unit axes ax_i, half extents h_i in w) is moved
// along the axis of least penetration to the face on its side (ties: the lower axis; l = 0:
// the + face)
vec3 collide_box(vec3 x, vec4 center, vec4 ax0, vec4 ax1, vec4 ax2)
{
    P vec3 d = x - center.xyz;
    P float l0 = dot3(d, ax0.xyz);  // the particle's coordinates along the box's axes
    P float l1 = dot3(d, ax1.xyz);
    P float l2 = dot3(d, ax2.xyz);
    P float p0 = ax0.w - abs(l0);  // the depth through each pair of faces
    P float p1 = ax1.w - abs(l1);
    P float p2 = ax2.w - abs(l2);
    if (p0 > 0.0 && p1 > 0.0 && p2 > 0.0) {
        vec3 axis = ax0.xyz;
        float least = p0, l = l0, h = ax0.w;
        if (p1 < least) {
            axis = ax1.xyz;
            least = p1;
            l = l1;
            h = ax1.w;
        }
        if (p2 < least) {
            axis = ax2.xyz;
            l = l2;
            h = ax2.w;
        }
        P float s = l >= 0.0 ? h : -h;
        P float move = s - l;
        P vec3 pushed = x + axis * move;
        return pushed;
    }
    return x;
}

vec3 collide_boxes(vec3 x)
{
    for (int i = 0; i < BOX_COUNT; ++i)
        x = collide_box(x, boxes[4 * i], boxes[4 * i + 1], boxes[4 * i + 2], boxes[4 * i + 3]);
    return x;
}
