#version 330
// The GCP marker pass (render.TileRenderer.render_markers): a marker's id as its colour (RGB) and
// three flags (alpha) that compare the fragment with the model's depth drawn before it, so that
// one draw and one read of the markers give what the model-first and marker-first passes gave.
uniform sampler2D u_model_depth;   // the model's window depth at this pass's pixels (1: nothing)
uniform float u_depth_span;        // metres of the window depth range
uniform float u_tolerance;         // metres: a marker this near the model's surface lies on it
uniform float u_seen_shift;        // window depth a marker is moved toward the camera to be seen
in vec4 v_color;
out vec4 f_color;
void main() {
    float model = texelFetch(u_model_depth, ivec2(gl_FragCoord.xy), 0).r;
    float z = gl_FragCoord.z;
    float flags = 0.0;
    if (model < 1.0) {                                                   // 1: over the model
        flags += 1.0;
        if (abs(model - z) * u_depth_span <= u_tolerance) flags += 2.0;  // 2: on its surface
    }
    if (z - u_seen_shift < model) flags += 4.0;                          // 4: in front of it (the depth test's <)
    f_color = vec4(v_color.rgb, flags / 255.0);
}
