// render_cloth.frag: the cloth, lit on both sides, with a checker pattern so folds show.
// Triangles are wound so that their front face is the side the normals point to
// (docs/normals.md); the back face is lit with the normal reversed and a paler colour.

uniform vec3 eye;       // camera position (m)
uniform vec3 light;     // unit vector toward the light
uniform float checks;   // checker squares per sheet side
uniform vec3 colour_a;  // the two checker colours of the front face
uniform vec3 colour_b;

in vec3 world;
in vec3 normal_v;
in vec2 sheet;
out vec4 colour;

void main()
{
    vec3 nrm = dot(normal_v, normal_v) > 0.0 ? normalize(normal_v)
                                             : normalize(cross(dFdx(world), dFdy(world)));
    ivec2 cell = ivec2(floor(sheet * checks));
    vec3 base = ((cell.x + cell.y) & 1) == 0 ? colour_a : colour_b;
    if (!gl_FrontFacing) {  // two-sided lighting: the back of the sheet faces the other way
        nrm = -nrm;
        base = mix(base, vec3(0.9), 0.35);
    }
    vec3 to_eye = normalize(eye - world);
    float diffuse = max(dot(nrm, light), 0.0);
    float specular = pow(max(dot(nrm, normalize(light + to_eye)), 0.0), 40.0);
    colour = vec4(base * (0.28 + 0.72 * diffuse) + 0.12 * specular, 1.0);
}
