//! The console's login form. It tells the truth about this server: where it listens (loopback or beyond) and
//! which file holds the operator token, so a person who lost the printed link knows where to look.
use askama::Template;
use libero_server::auth::LoginInfo;

#[derive(Template)]
#[template(path = "login.html")]
struct LoginPage {
    failed: bool,
    /// `127.0.0.1:8080`, or empty when unknown.
    listen: String,
    loopback_only: bool,
    /// The absolute path of `<data>/operator_token`, or empty when unknown.
    token_file: String,
}

pub fn login_page(info: &LoginInfo) -> String {
    let page = LoginPage {
        failed: info.failed,
        listen: info.listen.map(|a| a.to_string()).unwrap_or_default(),
        loopback_only: info.loopback_only,
        token_file: info.token_file.as_ref().map(|f| f.display().to_string()).unwrap_or_default(),
    };
    page.render().unwrap_or_else(|e| format!("template error: {e}"))
}
