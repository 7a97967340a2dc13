// render_collider.frag: a collider in one colour, or the floor with a 10 cm grid of tiles.

uniform vec3 eye;
uniform vec3 light;  // unit vector toward the light
uniform vec3 base;
uniform bool tiles;  // the floor: alternate two shades in 10 cm squares

in vec3 world;
in vec3 normal_v;
out vec4 colour;

void main()
{
    vec3 nrm = normalize(normal_v);
    vec3 c = base;
    if (tiles) {
        ivec3 cell = ivec3(floor(world * 10.0));
        c *= ((cell.x + cell.y + cell.z) & 1) == 0 ? 1.0 : 0.85;
    }
    float diffuse = max(dot(nrm, light), 0.0);
    float specular = pow(max(dot(nrm, normalize(light + normalize(eye - world))), 0.0), 30.0);
    colour = vec4(c * (0.3 + 0.7 * diffuse) + 0.2 * specular, 1.0);
}
