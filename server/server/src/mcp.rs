//! One episode's MCP server: `tools/list` from the episode crate's contract, `tools/call` forwarded to the
//! episode actor, results wrapped in the original envelope (§2.6).
use libero_episode::EpisodeHandle;
use libero_records::json::pretty_sorted;
use libero_records::records::ToolReply;
use libero_episode::tools::{PROTOCOL_VERSION, SERVER_INSTRUCTIONS, SERVER_NAME, SERVER_VERSION, tools_list};
use rmcp::model::{
    CallToolRequestParams, CallToolResponse, CallToolResult, ContentBlock, ErrorCode, Implementation, ListPromptsResult,
    ListResourcesResult, ListToolsResult,
    PaginatedRequestParams, ResultType, ServerCapabilities, ServerConfig,
};
use rmcp::service::RequestContext;
use rmcp::{ErrorData, RoleServer, ServerHandler};
use serde_json::{Value, json};

/// The handler rmcp builds per session (or per request in stateless mode): a handle clone, cheap.
#[derive(Clone)]
pub struct EpisodeMcp {
    pub handle: EpisodeHandle,
}

/// The tool result envelope: sorted pretty JSON text, the payload as `structuredContent`, and `isError`
/// unless `ok` is exactly `true`.
pub fn envelope(payload: Value) -> CallToolResult {
    let ok = ToolReply::of(&payload).is_ok();
    let mut result = CallToolResult::success(vec![ContentBlock::text(pretty_sorted(&payload))]);
    result.structured_content = Some(payload);
    result.is_error = Some(!ok);
    result
}

/// `tools/list` as rmcp's type (built from the same JSON as the golden fixture).
pub fn list_tools_result() -> Result<ListToolsResult, ErrorData> {
    let mut result: ListToolsResult = serde_json::from_value(tools_list())
        .map_err(|e| ErrorData::internal_error(format!("tool definitions do not parse: {e}"), None))?;
    // What rmcp's constructors set; required on 2026-07-28 connections, cleared by rmcp for older ones.
    result.result_type = Some(ResultType::COMPLETE);
    Ok(result)
}

pub fn server_config() -> ServerConfig {
    let capabilities: ServerCapabilities =
        serde_json::from_value(json!({"tools": {"listChanged": false}})).unwrap_or_default();
    let _ = PROTOCOL_VERSION; // rmcp negotiates the version with the client (it supports 2025-06-18)
    ServerConfig::new(capabilities)
        .with_server_info(Implementation::new(SERVER_NAME, SERVER_VERSION))
        .with_instructions(SERVER_INSTRUCTIONS)
}

/// The original adapter answers every method it does not implement with -32601 (§2.3).
fn method_not_found(method: &str) -> ErrorData {
    ErrorData::new(ErrorCode::METHOD_NOT_FOUND, format!("method not found: {method}"), None)
}

impl ServerHandler for EpisodeMcp {
    fn get_info(&self) -> ServerConfig {
        server_config()
    }

    async fn list_resources(
        &self,
        _request: Option<PaginatedRequestParams>,
        _context: RequestContext<RoleServer>,
    ) -> Result<ListResourcesResult, ErrorData> {
        Err(method_not_found("resources/list"))
    }

    async fn list_prompts(
        &self,
        _request: Option<PaginatedRequestParams>,
        _context: RequestContext<RoleServer>,
    ) -> Result<ListPromptsResult, ErrorData> {
        Err(method_not_found("prompts/list"))
    }

    async fn list_tools(
        &self,
        _request: Option<PaginatedRequestParams>,
        _context: RequestContext<RoleServer>,
    ) -> Result<ListToolsResult, ErrorData> {
        list_tools_result()
    }

    async fn call_tool(
        &self,
        request: CallToolRequestParams,
        _context: RequestContext<RoleServer>,
    ) -> Result<CallToolResponse, ErrorData> {
        let handle = self.handle.clone();
        let name = request.name.to_string();
        let arguments = request.arguments;
        // The actor blocks while it simulates and renders; keep that off the async workers.
        let payload = tokio::task::spawn_blocking(move || handle.call(&name, arguments))
            .await
            .unwrap_or_else(|_| libero_episode::ToolError::environment().payload());
        Ok(envelope(payload).into())
    }
}
