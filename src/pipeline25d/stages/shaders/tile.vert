
#version 330
uniform mat4 u_mvp;
uniform vec4 u_shear;        // clip-space shift per metre of ground height (terrain-relative mode)
uniform float u_zbias;
in vec3 in_pos;
in float in_ground;          // DTM height under the vertex minus its chunk origin's height (0 in plane mode)
in vec4 in_color;
in vec2 in_uv;
out vec3 v_pos;
out vec4 v_color;
out vec2 v_uv;
#ifdef SHADOWS
uniform mat4 u_sun_mvp;      // chunk-local -> shadow-map texels (u, w) and depth (-height, m)
out vec3 v_sun;
#endif
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0) - in_ground * u_shear;
    gl_Position.z -= u_zbias;
    v_pos = in_pos;
    v_color = in_color;
    v_uv = in_uv;
#ifdef SHADOWS
    v_sun = (u_sun_mvp * vec4(in_pos, 1.0)).xyz;   // the true 3D position, not the displaced one
#endif
}
