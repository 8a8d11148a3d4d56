
#version 330
uniform int u_mode;          // 0 vertex colour, 1 texture, 2 uniform colour
uniform vec4 u_color;
uniform sampler2D u_tex;
uniform bool u_shade;
uniform vec3 u_light;        // direction the light travels
uniform vec3 u_view;         // direction the camera looks
uniform float u_ambient;
in vec3 v_pos;
in vec4 v_color;
in vec2 v_uv;
layout(location = 0) out vec4 f_color;
#ifdef IDS
uniform usampler2D u_faces;       // the object id of every face, FACE_WIDTH a row (render_ids.py)
layout(location = 1) out uint f_id;
#endif
#ifdef SHADOWS
uniform bool u_sunlit;            // this pass is lit by the sun (the colour pass)
uniform sampler2D u_shadow_map;   // depth seen from the sun, window depth in [0, 1]
uniform vec3 u_sun;               // unit vector toward the sun
uniform vec3 u_sun_u;             // scene metres of one shadow-map texel along u
uniform vec3 u_sun_w;             // ... and along w
uniform float u_depth_span;       // metres of the shadow map's depth range (heights)
uniform float u_bias;             // metres
uniform float u_radius;           // tent filter radius, texels
uniform float u_shadow_ambient;   // brightness in shadow, as a share of full sun
in vec3 v_sun;                    // texels from the shadow map's corner (u, w); depth from its near plane (m)

// Share of the sun reaching a face of normal n here: depth comparisons at the texel centres
// within u_radius, weighted by a tent filter (continuous in position: soft edges, and the same
// value wherever the same point is drawn). Each comparison is against this face's own plane
// continued to that texel (receiver-plane depth), less a constant bias.
float sunlight(vec3 n) {
    float facing = dot(n, u_sun);
    if (facing <= 0.0) return 0.0;                      // the face turns away from the sun
    vec2 slope = vec2(dot(n, u_sun_u), dot(n, u_sun_w)) / max(facing, 0.02);   // metres of depth per texel
    ivec2 last = textureSize(u_shadow_map, 0) - 1;
    ivec2 lo = ivec2(ceil(v_sun.xy - 0.5 - u_radius));
    ivec2 hi = ivec2(floor(v_sun.xy - 0.5 + u_radius));
    float lit = 0.0;
    float total = 0.0;
    for (int j = lo.y; j <= hi.y; ++j) {
        for (int i = lo.x; i <= hi.x; ++i) {
            vec2 delta = vec2(i, j) + 0.5 - v_sun.xy;
            float w = max(1.0 - abs(delta.x) / u_radius, 0.0) * max(1.0 - abs(delta.y) / u_radius, 0.0);
            float stored = texelFetch(u_shadow_map, clamp(ivec2(i, j), ivec2(0), last), 0).r * u_depth_span;
            lit += w * step(v_sun.z + dot(slope, delta) - u_bias, stored);
            total += w;
        }
    }
    return total > 0.0 ? lit / total : 1.0;
}
#endif
void main() {
    vec4 base = u_mode == 0 ? v_color : (u_mode == 1 ? texture(u_tex, v_uv) : u_color);
    float shade = 1.0;
#ifdef SHADOWS
    if (u_sunlit) {
        vec3 n = normalize(cross(dFdx(v_pos), dFdy(v_pos)));
        if (dot(n, u_view) > 0.0) n = -n;   // the face the camera sees
        float sun = sunlight(n);
        if (u_shade) sun *= max(dot(n, u_sun), 0.0);   // untextured: Lambert by the sun
        shade = u_shadow_ambient + (1.0 - u_shadow_ambient) * sun;
    } else
#endif
    if (u_shade) {
        vec3 n = normalize(cross(dFdx(v_pos), dFdy(v_pos)));
        if (dot(n, u_view) > 0.0) n = -n;   // the face the camera sees
        shade = u_ambient + (1.0 - u_ambient) * max(dot(n, -u_light), 0.0);
    }
    f_color = vec4(base.rgb * shade, 1.0);
#ifdef IDS
    f_id = texelFetch(u_faces, ivec2(gl_PrimitiveID % FACE_WIDTH, gl_PrimitiveID / FACE_WIDTH), 0).r;
#endif
}
