// A game's `StandardMaterial` under the clouds (docs/illumination.md §10): Bevy's PBR, each
// cloud-lighting directional light seen through the clouds' shadow maps, and Bevy's ambient light
// (the sky) through the sky map. Bevy's lighting has no per-light hook, so the surface is lit as
// Bevy lights it, and then what the clouds hold back is taken away: per light, (1 - T) of its
// contribution, which Bevy's own `directional_light` and shadow map give; of the ambient light,
// (1 - V) of Bevy's own `ambient_light`. Lighting is linear in each light, so this is exact.
// Rust mirror: src/cloud_shadowed_material.rs; the lights and maps: cloud_shadow_maps.wgsl.
#import bevy_pbr::{
    pbr_fragment::pbr_input_from_standard_material,
    pbr_functions::alpha_discard,
    decal::clustered::apply_decals,
}
#import bevy_particle_clouds::cloud_shadow_maps::{lights, cloud_transmittance, sky_visibility}

#ifdef PREPASS_PIPELINE
#import bevy_pbr::{
    prepass_io::{VertexOutput, FragmentOutput},
    pbr_deferred_functions::deferred_output,
}
#else
#import bevy_pbr::{
    forward_io::{VertexOutput, FragmentOutput},
    pbr_functions::{
        apply_pbr_lighting, main_pass_post_lighting_processing, calculate_diffuse_color,
        calculate_F0_dielectric, calculate_F0,
    },
    ambient,
    pbr_types::{PbrInput, STANDARD_MATERIAL_FLAGS_UNLIT_BIT},
    lighting,
    lighting::{LAYER_BASE, LAYER_CLEARCOAT},
    shadows::fetch_directional_shadow,
    mesh_types::MESH_FLAGS_SHADOW_RECEIVER_BIT,
    mesh_view_types::DIRECTIONAL_LIGHT_FLAGS_SHADOWS_ENABLED_BIT,
    mesh_view_bindings as view_bindings,
}
#ifdef LIGHTMAP
#import bevy_pbr::mesh_view_types::DIRECTIONAL_LIGHT_FLAGS_AFFECTS_LIGHTMAPPED_MESH_DIFFUSE_BIT
#endif
#ifdef CONTACT_SHADOWS
#ifdef DEPTH_PREPASS
#import bevy_pbr::{
    pbr_functions::calculate_contact_shadow,
    mesh_view_types::DIRECTIONAL_LIGHT_FLAGS_CONTACT_SHADOWS_ENABLED_BIT,
}
#endif
#endif

const NO_CLOUD_LIGHT: u32 = 0xffffffffu;

// The cloud-lighting light that travels as Bevy's light towards `to_light` does: the same light
// (or one its maps would equal); NO_CLOUD_LIGHT for a light the clouds do not take.
fn cloud_light_of(to_light: vec3<f32>) -> u32 {
    for (var l = 0u; l < lights.count; l++) {
        if dot(lights.lights[l].to_light, to_light) > 0.99999 {
            return l;
        }
    }
    return NO_CLOUD_LIGHT;
}

// The surface as `apply_pbr_lighting` describes it to its lights.
fn lighting_input(in: PbrInput) -> lighting::LightingInput {
    var input: lighting::LightingInput;
    let NdotV = max(dot(in.N, in.V), 0.0001);
    let perceptual_roughness = in.material.perceptual_roughness;
    input.layers[LAYER_BASE].NdotV = NdotV;
    input.layers[LAYER_BASE].N = in.N;
    input.layers[LAYER_BASE].R = reflect(-in.V, in.N);
    input.layers[LAYER_BASE].perceptual_roughness = perceptual_roughness;
    input.layers[LAYER_BASE].roughness = lighting::perceptualRoughnessToRoughness(perceptual_roughness);
    input.P = in.world_position.xyz;
    input.V = in.V;
    input.diffuse_color = calculate_diffuse_color(
        in.material.base_color.rgb,
        in.material.metallic,
        in.material.specular_transmission,
        in.material.diffuse_transmission,
    );
    input.metallic = in.material.metallic;
    input.F0_dielectric = calculate_F0_dielectric(in.material.reflectance);
    input.F0_metallic = in.material.base_color.rgb;
    input.F_ab = lighting::F_AB(perceptual_roughness, NdotV);
#ifdef STANDARD_MATERIAL_CLEARCOAT
    let coat_roughness = in.material.clearcoat_perceptual_roughness;
    input.layers[LAYER_CLEARCOAT].NdotV = max(dot(in.clearcoat_N, in.V), 0.0001);
    input.layers[LAYER_CLEARCOAT].N = in.clearcoat_N;
    input.layers[LAYER_CLEARCOAT].R = reflect(-in.V, in.clearcoat_N);
    input.layers[LAYER_CLEARCOAT].perceptual_roughness = coat_roughness;
    input.layers[LAYER_CLEARCOAT].roughness = lighting::perceptualRoughnessToRoughness(coat_roughness);
    input.clearcoat_strength = in.material.clearcoat;
#endif
#ifdef STANDARD_MATERIAL_ANISOTROPY
    input.anisotropy = in.anisotropy_strength;
    input.Ta = in.anisotropy_T;
    input.Ba = in.anisotropy_B;
#endif
    return input;
}

// Bevy's shadow of light `i` at the surface (its shadow map, and contact shadows where on).
fn bevy_shadow(in: PbrInput, i: u32, view_z: f32) -> f32 {
    let flags = view_bindings::lights.directional_lights[i].flags;
    var shadow = 1.0;
    if (in.flags & MESH_FLAGS_SHADOW_RECEIVER_BIT) != 0u
            && (flags & DIRECTIONAL_LIGHT_FLAGS_SHADOWS_ENABLED_BIT) != 0u {
        shadow = fetch_directional_shadow(i, in.world_position, in.world_normal, view_z, in.frag_coord.xy);
    }
#ifdef CONTACT_SHADOWS
#ifdef DEPTH_PREPASS
    let steps = view_bindings::contact_shadows_settings.linear_steps;
    if steps > 0u && (in.flags & MESH_FLAGS_SHADOW_RECEIVER_BIT) != 0u && shadow > 0.0
            && (flags & DIRECTIONAL_LIGHT_FLAGS_CONTACT_SHADOWS_ENABLED_BIT) != 0u {
        let to_light = view_bindings::lights.directional_lights[i].direction_to_light;
        shadow *= calculate_contact_shadow(in.world_position.xyz, in.frag_coord.xy, to_light, steps);
    }
#endif
#endif
    return shadow;
}

// What the clouds hold back of the light (before exposure): per cloud-lighting light, (1 - T) of
// what it brings the surface in Bevy's lighting; and of the ambient light.
fn held_back_by_clouds(in: PbrInput) -> vec3<f32> {
    var input = lighting_input(in);
    let view_z = dot(vec4(
        view_bindings::view.view_from_world[0].z,
        view_bindings::view.view_from_world[1].z,
        view_bindings::view.view_from_world[2].z,
        view_bindings::view.view_from_world[3].z,
    ), in.world_position);
    var held = vec3(0.0);
    for (var i = 0u; i < view_bindings::lights.n_directional_lights; i++) {
        let light = &view_bindings::lights.directional_lights[i];
        let l = cloud_light_of((*light).direction_to_light);
        if l == NO_CLOUD_LIGHT {
            continue;
        }
        let transmittance = cloud_transmittance(l, in.world_position.xyz);
        if transmittance >= 1.0 {
            continue;
        }
#ifdef LIGHTMAP
        let enable_diffuse =
            ((*light).flags & DIRECTIONAL_LIGHT_FLAGS_AFFECTS_LIGHTMAPPED_MESH_DIFFUSE_BIT) != 0u;
#else
        let enable_diffuse = true;
#endif
        let contribution = lighting::directional_light(i, &input, enable_diffuse);
        held += (1.0 - transmittance) * bevy_shadow(in, i, view_z) * contribution;
    }
    return held + sky_held_back(in, input);
}

// What the clouds hold back of Bevy's ambient light, which stands for the sky: (1 - V) of it,
// `V` what the sky map leaves of the sky (1 without a sky map: no `CloudSkyLight`).
fn sky_held_back(in: PbrInput, input: lighting::LightingInput) -> vec3<f32> {
#ifdef LIGHTMAP
    // As Bevy: a lightmap may hold the ambient light already.
    if view_bindings::lights.ambient_light_affects_lightmapped_meshes == 0u {
        return vec3(0.0);
    }
#endif
    let hidden = 1.0 - sky_visibility(in.world_position.xyz);
    if hidden <= 0.0 {
        return vec3(0.0);
    }
    let F0 = calculate_F0(in.material.base_color.rgb, in.material.metallic, in.material.reflectance);
    let NdotV = input.layers[LAYER_BASE].NdotV;
    let perceptual_roughness = in.material.perceptual_roughness;
    return hidden * ambient::ambient_light(
        in.world_position, in.N, in.V, NdotV, input.diffuse_color, F0, perceptual_roughness,
        in.diffuse_occlusion,
    );
}
#endif

@fragment
fn fragment(in: VertexOutput, @builtin(front_facing) is_front: bool) -> FragmentOutput {
    var pbr_input = pbr_input_from_standard_material(in, is_front);
    pbr_input.material.base_color = alpha_discard(pbr_input.material, pbr_input.material.base_color);
    apply_decals(&pbr_input);
#ifdef PREPASS_PIPELINE
    // Deferred: Bevy lights the G-buffer in its own pass, which cannot read the maps.
    let out = deferred_output(in, pbr_input);
#else
    var out: FragmentOutput;
    if (pbr_input.material.flags & STANDARD_MATERIAL_FLAGS_UNLIT_BIT) == 0u {
        let lit = apply_pbr_lighting(pbr_input);
        let held = view_bindings::view.exposure * held_back_by_clouds(pbr_input);
        // max: f32 rounding must not take a fully shadowed surface below black.
        out.color = vec4(max(lit.rgb - held, vec3(0.0)), lit.a);
    } else {
        out.color = pbr_input.material.base_color;
    }
    out.color = main_pass_post_lighting_processing(pbr_input, out.color);
#endif
    return out;
}
