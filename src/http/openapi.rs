//! The OpenAPI 3 document of the HTTP API (`GET /openapi.json`).
//!
//! Its schemas are generated from the proto's descriptors (the same ones reflection serves),
//! field by field in the form pbjson writes and reads them — lowerCamelCase names, 64-bit
//! integers as strings, bytes as base64, enums by name, default values omitted — with each
//! field's proto comment as its description. Only the routes are written here, so the proto
//! stays the one contract and the document cannot drift from the messages the server parses.

use prost::Message;
use prost_types::field_descriptor_proto::{Label, Type};
use prost_types::{DescriptorProto, EnumDescriptorProto, FileDescriptorSet};
use serde_json::{Map, Value, json};

use crate::grpc::proto::FILE_DESCRIPTOR_SET;

/// The proto package whose messages the API speaks.
const PACKAGE: &str = "posematch.v1";

/// The error codes an answer may carry (`ErrorBody.code`).
const ERROR_CODES: &[&str] = &[
    "INVALID_ARGUMENT",
    "UNAUTHENTICATED",
    "NOT_FOUND",
    "ALREADY_EXISTS",
    "OUT_OF_RANGE",
    "RESOURCE_EXHAUSTED",
    "UNAVAILABLE",
    "DEADLINE_EXCEEDED",
    "UNIMPLEMENTED",
    "INTERNAL",
];

/// The whole document.
pub fn openapi_document() -> Value {
    let set = FileDescriptorSet::decode(FILE_DESCRIPTOR_SET)
        .expect("the descriptor set compiled into the binary decodes");
    let mut schemas = Map::new();
    for file in set.file.iter().filter(|f| f.package() == PACKAGE) {
        let comments = Comments::of(file);
        for (index, message) in file.message_type.iter().enumerate() {
            add_message(&mut schemas, "", message, &comments, &[4, index as i32]);
        }
        for (index, enumeration) in file.enum_type.iter().enumerate() {
            add_enum(&mut schemas, "", enumeration, &comments, &[5, index as i32]);
        }
    }
    schemas.insert(
        "Error".into(),
        json!({
            "type": "object",
            "description": "Every failed call's body. `code` is the gRPC status code's name.",
            "properties": {
                "code": {"type": "string", "enum": ERROR_CODES},
                "message": {"type": "string", "description": "What went wrong and what to fix."}
            },
            "required": ["code", "message"],
            "additionalProperties": false
        }),
    );
    json!({
        "openapi": "3.0.3",
        "info": {
            "title": "PoseMatch",
            "version": "v1",
            "description": "Find registered templates in camera images and get every instance's in-plane pose. The same API as the gRPC service posematch.v1.PoseMatcher (proto/posematch/v1/posematch.proto): each body is that RPC's message in the proto3 JSON mapping (lowerCamelCase names, the proto's own names also accepted; bytes as base64; 64-bit integers as strings; enums by name; fields at their default value left out). When the server has an auth_tokens_file, every /v1 call needs `Authorization: Bearer <token>`."
        },
        "paths": paths(),
        "components": {
            "schemas": schemas,
            "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}},
            "responses": error_responses(),
        },
        "security": [{"bearer": []}, {}],
    })
}

/// The routes, each naming the message its body and answer hold.
fn paths() -> Value {
    let template_id = json!({
        "name": "template_id", "in": "path", "required": true,
        "schema": {"type": "string", "minLength": 1},
        "description": "A registered template's ID (percent-encoded)."
    });
    let calibration_id = json!({
        "name": "calibration_id", "in": "path", "required": true,
        "schema": {"type": "string", "minLength": 1},
        "description": "A registered calibration's ID (percent-encoded)."
    });
    let page = json!([
        {"name": "pageSize", "in": "query", "schema": {"type": "integer", "minimum": 0, "maximum": 1000},
         "description": "0 means 100; at most 1000."},
        {"name": "pageToken", "in": "query", "schema": {"type": "string"},
         "description": "From the previous page's nextPageToken; empty for the first page."}
    ]);
    let timeout = json!({
        "name": "grpc-timeout", "in": "header", "required": false,
        "schema": {"type": "string", "pattern": "^[0-9]{1,8}[HMSmun]$"},
        "description": "The request's deadline as gRPC writes it (\"250m\" = 250 ms): past it the call ends with 504 DEADLINE_EXCEEDED. To always get an answer, set the options' timeoutMs below it."
    });
    let (template, frame) = example_images();
    let register = with_example(
        with_links(
            operation(
                "RegisterTemplate",
                "Registers a template: encodes it once and persists it. The same image under the same ID again is a no-op; a different image under an existing ID is 409 ALREADY_EXISTS unless `replace`.",
                Some("RegisterTemplateRequest"),
                "TemplateInfo",
                &[400, 401, 409, 413, 429, 503, 504],
            ),
            "template_id",
            "templateId",
            "GetTemplate",
            "DeleteTemplate",
        ),
        json!({"templateId": "example-part", "image": template, "labels": {"line": "4"}}),
    );
    let match_image = with_example(
        operation(
            "Match",
            "Finds one registered template (templateId) or several (templateIds) in one image and returns every instance's pose.",
            Some("MatchRequest"),
            "MatchResponse",
            &[400, 401, 404, 413, 429, 503, 504],
        ),
        json!({"templateId": "example-part", "image": frame, "options": {"maxInstances": 2}, "requestId": "frame-1"}),
    );
    let register_calibration = with_example(
        with_links(
            operation(
                "RegisterCalibration",
                "Registers the map from image pixels to a world plane that MatchOptions.calibrationId refers to.",
                Some("RegisterCalibrationRequest"),
                "CalibrationInfo",
                &[400, 401, 409, 413, 503, 504],
            ),
            "calibration_id",
            "calibrationId",
            "GetCalibration",
            "DeleteCalibration",
        ),
        json!({"calibrationId": "belt-1", "unit": "mm", "points": [
            {"imageX": 0, "imageY": 0, "worldX": 0, "worldY": 0},
            {"imageX": 100, "imageY": 0, "worldX": 25, "worldY": 0},
            {"imageX": 0, "imageY": 100, "worldX": 0, "worldY": 25}]}),
    );
    json!({
        "/v1/templates": {
            "post": register,
            "get": with_parameters(operation("ListTemplates", "Lists registered templates, a page at a time, in ID order.",
                None, "ListTemplatesResponse", &[400, 401, 503]), page.clone()),
        },
        "/v1/templates/{template_id}": {
            "get": with_parameters(operation("GetTemplate", "One template's description; with includeImage=true also its stored image (and mask), exactly as Match uses them.",
                None, "TemplateInfo", &[400, 401, 404, 503]),
                json!([template_id, {"name": "includeImage", "in": "query", "schema": {"type": "boolean"},
                    "description": "Also return the stored image (TemplateInfo.image)."}])),
            "delete": with_parameters(operation("DeleteTemplate", "Deletes a template; `deleted` is left out (false) when there was none.",
                None, "DeleteTemplateResponse", &[400, 401, 503]), json!([template_id])),
        },
        "/v1/match": {
            "post": with_parameters(match_image, json!([timeout])),
        },
        "/v1/calibrations": {
            "post": register_calibration,
            "get": with_parameters(operation("ListCalibrations", "Lists registered calibrations, a page at a time.",
                None, "ListCalibrationsResponse", &[400, 401, 503]), page),
        },
        "/v1/calibrations/{calibration_id}": {
            "get": with_parameters(operation("GetCalibration", "One calibration.",
                None, "CalibrationInfo", &[400, 401, 404, 503]), json!([calibration_id])),
            "delete": with_parameters(operation("DeleteCalibration", "Deletes a calibration; `deleted` is left out (false) when there was none.",
                None, "DeleteCalibrationResponse", &[400, 401, 503]), json!([calibration_id])),
        },
    })
}

/// One operation: its body (a message), its answer, and the error statuses it may give.
fn operation(rpc: &str, summary: &str, body: Option<&str>, answer: &str, errors: &[u16]) -> Value {
    let mut responses = Map::new();
    responses.insert(
        "200".into(),
        json!({"description": "OK", "content": {"application/json": {"schema": reference(answer)}}}),
    );
    // Every operation with a body refuses other content types (415): see `require_json`.
    let refused_type: &[u16] = if body.is_some() { &[415] } else { &[] };
    for status in errors.iter().chain(refused_type).chain(&[500]) {
        responses.insert(
            status.to_string(),
            json!({"$ref": format!("#/components/responses/{status}")}),
        );
    }
    let mut operation = json!({
        "operationId": rpc,
        "summary": summary,
        "responses": responses,
    });
    if let Some(body) = body {
        operation["requestBody"] = json!({
            "required": true,
            "content": {"application/json": {"schema": reference(body)}}
        });
    }
    operation
}

/// A request body example that works as it stands (the examples register a template, match it
/// in a frame, register a calibration), for readers and for fuzzers' first requests.
fn with_example(mut operation: Value, example: Value) -> Value {
    operation["requestBody"]["content"]["application/json"]["example"] = example;
    operation
}

/// OpenAPI links from a registration's answer to the routes that take the registered ID.
fn with_links(
    mut operation: Value,
    parameter: &str,
    field: &str,
    get: &str,
    delete: &str,
) -> Value {
    let link = |target: &str| json!({"operationId": target, "parameters": {parameter: format!("$response.body#/{field}")}});
    operation["responses"]["200"]["links"] = json!({get: link(get), delete: link(delete)});
    operation
}

/// A textured 96x96 frame and a 24x24 crop of it at (30, 40), as proto3 JSON `Image`s.
fn example_images() -> (Value, Value) {
    let frame = image::RgbImage::from_fn(96, 96, |x, y| {
        let (fx, fy) = (x as f32, y as f32);
        let a = ((fx * 0.21).sin() * (fy * 0.17).cos() * 0.5 + 0.5) * 255.0;
        let b = ((fx * 0.07 + fy * 0.13).sin() * 0.5 + 0.5) * 255.0;
        let c = (((x / 9 + y / 7) % 3) * 100) as f32;
        image::Rgb([a as u8, b as u8, c as u8])
    });
    let template = image::imageops::crop_imm(&frame, 30, 40, 24, 24).to_image();
    let as_json = |picture: &image::RgbImage| {
        let mut png = Vec::new();
        picture
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .expect("a PNG encodes in memory");
        let image = crate::grpc::proto::Image {
            data: Some(crate::grpc::proto::image::Data::Encoded(png)),
        };
        serde_json::to_value(image).expect("an Image serialises")
    };
    (as_json(&template), as_json(&frame))
}

fn with_parameters(mut operation: Value, parameters: Value) -> Value {
    operation["parameters"] = parameters;
    operation
}

fn error_responses() -> Value {
    let described = [
        (
            400,
            "The request is not valid (INVALID_ARGUMENT): a body that is not the message in JSON, a bad option, an undecodable image; the message says what to fix.",
        ),
        (401, "No valid bearer token (UNAUTHENTICATED)."),
        (404, "No such template or calibration (NOT_FOUND)."),
        (
            409,
            "A different template or calibration is registered under this ID (ALREADY_EXISTS): set `replace`.",
        ),
        (
            413,
            "The body is larger than the server takes (OUT_OF_RANGE).",
        ),
        (
            415,
            "The body was not sent with `Content-Type: application/json` (INVALID_ARGUMENT): other types are refused so that other web pages cannot post to this API.",
        ),
        (
            429,
            "The match queue is full (RESOURCE_EXHAUSTED): retry later.",
        ),
        (500, "A fault of the server (INTERNAL)."),
        (
            503,
            "Not ready (UNAVAILABLE): the model is still loading or the template store cannot be reached; retry.",
        ),
        (504, "The grpc-timeout deadline passed (DEADLINE_EXCEEDED)."),
    ];
    let mut responses = Map::new();
    for (status, description) in described {
        responses.insert(
            status.to_string(),
            json!({"description": description, "content": {"application/json": {"schema": reference("Error")}}}),
        );
    }
    Value::Object(responses)
}

fn reference(schema: &str) -> Value {
    json!({"$ref": format!("#/components/schemas/{schema}")})
}

/// Leading comments by descriptor path (SourceCodeInfo).
struct Comments(std::collections::HashMap<Vec<i32>, String>);

impl Comments {
    fn of(file: &prost_types::FileDescriptorProto) -> Self {
        let mut comments = std::collections::HashMap::new();
        for location in file.source_code_info.iter().flat_map(|info| &info.location) {
            if let Some(text) = &location.leading_comments {
                let text = text.split_whitespace().collect::<Vec<_>>().join(" ");
                if !text.is_empty() {
                    comments.insert(location.path.clone(), text);
                }
            }
        }
        Self(comments)
    }

    fn at(&self, path: &[i32]) -> Option<&String> {
        self.0.get(path)
    }
}

fn add_message(
    schemas: &mut Map<String, Value>,
    prefix: &str,
    message: &DescriptorProto,
    comments: &Comments,
    path: &[i32],
) {
    let name = format!("{prefix}{}", message.name());
    if message.options.as_ref().is_some_and(|o| o.map_entry()) {
        return; // written inline as its map's additionalProperties
    }
    let map_entries: std::collections::HashMap<&str, &DescriptorProto> = message
        .nested_type
        .iter()
        .filter(|nested| nested.options.as_ref().is_some_and(|o| o.map_entry()))
        .map(|nested| (nested.name(), nested))
        .collect();
    let mut properties = Map::new();
    for (index, field) in message.field.iter().enumerate() {
        let entry = field
            .type_name()
            .rsplit('.')
            .next()
            .and_then(|short| map_entries.get(short));
        let mut schema = match entry {
            Some(entry) if field.r#type() == Type::Message => {
                let value = &entry.field[1];
                json!({"type": "object", "additionalProperties": scalar_or_reference(value)})
            }
            _ if field.label() == Label::Repeated => {
                json!({"type": "array", "items": scalar_or_reference(field)})
            }
            _ => scalar_or_reference(field),
        };
        let mut field_path = path.to_vec();
        field_path.extend([2, index as i32]);
        if let Some(text) = comments.at(&field_path) {
            describe(&mut schema, text);
        }
        properties.insert(field.json_name().to_owned(), schema);
    }
    let mut schema = json!({
        "type": "object",
        "properties": properties,
        "additionalProperties": false,
    });
    if let Some(text) = comments.at(path) {
        schema["description"] = Value::String(text.clone());
    }
    schemas.insert(name.clone(), schema);
    let nested_prefix = format!("{name}.");
    for (index, nested) in message.nested_type.iter().enumerate() {
        let mut nested_path = path.to_vec();
        nested_path.extend([3, index as i32]);
        add_message(schemas, &nested_prefix, nested, comments, &nested_path);
    }
    for (index, enumeration) in message.enum_type.iter().enumerate() {
        let mut enum_path = path.to_vec();
        enum_path.extend([4, index as i32]);
        add_enum(schemas, &nested_prefix, enumeration, comments, &enum_path);
    }
}

fn add_enum(
    schemas: &mut Map<String, Value>,
    prefix: &str,
    enumeration: &EnumDescriptorProto,
    comments: &Comments,
    path: &[i32],
) {
    let names: Vec<&str> = enumeration.value.iter().map(|v| v.name()).collect();
    let mut schema = json!({"type": "string", "enum": names});
    let described: Vec<String> = enumeration
        .value
        .iter()
        .enumerate()
        .filter_map(|(index, value)| {
            let mut value_path = path.to_vec();
            value_path.extend([2, index as i32]);
            comments
                .at(&value_path)
                .map(|text| format!("{}: {text}", value.name()))
        })
        .collect();
    let mut text = comments.at(path).cloned().unwrap_or_default();
    for line in described {
        if !text.is_empty() {
            text.push(' ');
        }
        text.push_str(&line);
    }
    if !text.is_empty() {
        schema["description"] = Value::String(text);
    }
    schemas.insert(format!("{prefix}{}", enumeration.name()), schema);
}

/// A field's schema as pbjson writes it (descriptions added by the caller).
fn scalar_or_reference(field: &prost_types::FieldDescriptorProto) -> Value {
    match field.r#type() {
        Type::Double | Type::Float => json!({"type": "number"}),
        Type::Int64 | Type::Sint64 | Type::Sfixed64 => {
            json!({"type": "string", "format": "int64", "pattern": "^-?[0-9]+$"})
        }
        Type::Uint64 | Type::Fixed64 => {
            json!({"type": "string", "format": "uint64", "pattern": "^[0-9]+$"})
        }
        Type::Int32 | Type::Sint32 | Type::Sfixed32 => {
            json!({"type": "integer", "format": "int32"})
        }
        Type::Uint32 | Type::Fixed32 => {
            json!({"type": "integer", "minimum": 0, "maximum": 4294967295_u64})
        }
        Type::Bool => json!({"type": "boolean"}),
        Type::String => json!({"type": "string"}),
        Type::Bytes => json!({"type": "string", "format": "byte"}),
        Type::Enum | Type::Message | Type::Group => {
            let name = field
                .type_name()
                .trim_start_matches('.')
                .trim_start_matches(PACKAGE)
                .trim_start_matches('.');
            reference(name)
        }
    }
}

/// Adds a description to a schema; a `$ref` cannot carry siblings in OpenAPI 3.0, so it is
/// wrapped in `allOf`.
fn describe(schema: &mut Value, text: &str) {
    if schema.get("$ref").is_some() {
        *schema = json!({"allOf": [schema.clone()], "description": text});
    } else {
        schema["description"] = Value::String(text.to_owned());
    }
}
