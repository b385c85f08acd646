//! The small YAML subset that calibration files use: block mappings by indentation,
//! scalars, flow sequences `[a, b]` (possibly over several lines), flow mappings
//! `{k: v}`, tags (`!!opencv-matrix`), comments, the `%YAML:1.0` directive and `---`.
//! Enough for OpenCV FileStorage YAML and ROS camera_info files; anything else is an
//! error with its line number.

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Node {
    Scalar(String),
    Seq(Vec<String>),
    Map(Vec<(String, Node)>),
}

impl Node {
    pub(crate) fn get(&self, key: &str) -> Option<&Node> {
        match self {
            Node::Map(entries) => entries.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }
}

/// A parse error: line (1-based) and reason.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ParseError {
    pub line: usize,
    pub reason: String,
}

struct Line<'a> {
    no: usize,
    indent: usize,
    text: &'a str,
}

fn strip_comment(s: &str) -> &str {
    let mut in_quote: Option<char> = None;
    let mut prev_space = true;
    for (i, ch) in s.char_indices() {
        match in_quote {
            Some(q) if ch == q => in_quote = None,
            Some(_) => {}
            None if ch == '"' || ch == '\'' => in_quote = Some(ch),
            None if ch == '#' && prev_space => return &s[..i],
            None => {}
        }
        prev_space = ch.is_whitespace();
    }
    s
}

fn unquote(s: &str) -> String {
    let s = s.trim();
    if s.len() >= 2
        && ((s.starts_with('"') && s.ends_with('"')) || (s.starts_with('\'') && s.ends_with('\'')))
    {
        s[1..s.len() - 1].to_string()
    } else {
        s.to_string()
    }
}

/// Split "a, b, {c: d}" at top-level commas.
fn split_flow(s: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let (mut depth, mut start) = (0i32, 0usize);
    for (i, ch) in s.char_indices() {
        match ch {
            '[' | '{' => depth += 1,
            ']' | '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(&s[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    out.push(&s[start..]);
    out.into_iter().filter(|p| !p.trim().is_empty()).collect()
}

/// Nesting (block mappings by indentation, and flow mappings) deeper than this is an
/// error: a calibration file needs three levels, and recursion must not overflow the
/// stack on a hostile file.
pub(crate) const MAX_DEPTH: usize = 32;

fn too_deep(line: usize) -> ParseError {
    ParseError {
        line,
        reason: format!("nested deeper than {MAX_DEPTH} levels"),
    }
}

fn parse_flow(text: &str, line: usize, depth: usize) -> Result<Node, ParseError> {
    if depth > MAX_DEPTH {
        return Err(too_deep(line));
    }
    let t = text.trim();
    let err = |reason: &str| ParseError {
        line,
        reason: reason.to_string(),
    };
    if let Some(inner) = t.strip_prefix('[') {
        let inner = inner
            .strip_suffix(']')
            .ok_or_else(|| err("unterminated '['"))?;
        let mut items = Vec::new();
        for p in split_flow(inner) {
            if p.trim_start().starts_with(['[', '{']) {
                return Err(err("nested collections in a sequence are not supported"));
            }
            items.push(unquote(p));
        }
        Ok(Node::Seq(items))
    } else if let Some(inner) = t.strip_prefix('{') {
        let inner = inner
            .strip_suffix('}')
            .ok_or_else(|| err("unterminated '{'"))?;
        let mut entries = Vec::new();
        for p in split_flow(inner) {
            let (k, v) = p
                .split_once(':')
                .ok_or_else(|| err("expected 'key: value' in a flow mapping"))?;
            entries.push((unquote(k), parse_flow(v, line, depth + 1)?));
        }
        Ok(Node::Map(entries))
    } else {
        Ok(Node::Scalar(unquote(strip_tag(t))))
    }
}

fn strip_tag(s: &str) -> &str {
    let s = s.trim();
    if s.starts_with('!') {
        match s.split_once(char::is_whitespace) {
            Some((_, rest)) => rest.trim(),
            None => "",
        }
    } else {
        s
    }
}

fn bracket_balance(s: &str) -> i64 {
    s.chars().fold(0, |d, c| match c {
        '[' | '{' => d + 1,
        ']' | '}' => d - 1,
        _ => d,
    })
}

/// Parse a whole document into its top-level mapping.
pub(crate) fn parse(text: &str) -> Result<Node, ParseError> {
    let mut lines = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let no = i + 1;
        if raw.starts_with('\t') {
            return Err(ParseError {
                line: no,
                reason: "tab used for indentation".into(),
            });
        }
        let body = strip_comment(raw);
        let trimmed = body.trim();
        if trimmed.is_empty() || trimmed.starts_with('%') || trimmed == "---" || trimmed == "..." {
            continue;
        }
        let indent = body.len() - body.trim_start().len();
        lines.push(Line {
            no,
            indent,
            text: trimmed,
        });
    }
    let mut pos = 0;
    let root = parse_map(&lines, &mut pos, 0, 0)?;
    if let Some(l) = lines.get(pos) {
        return Err(ParseError {
            line: l.no,
            reason: "unexpected indentation".into(),
        });
    }
    Ok(root)
}

fn parse_map(
    lines: &[Line<'_>],
    pos: &mut usize,
    indent: usize,
    depth: usize,
) -> Result<Node, ParseError> {
    let mut entries: Vec<(String, Node)> = Vec::new();
    // Keys seen, for the duplicate check in constant time per key.
    let mut keys = std::collections::HashSet::new();
    while let Some(l) = lines.get(*pos) {
        if depth > MAX_DEPTH {
            return Err(too_deep(l.no));
        }
        if l.indent < indent {
            break;
        }
        if l.indent > indent {
            return Err(ParseError {
                line: l.no,
                reason: "unexpected indentation".into(),
            });
        }
        if l.text.starts_with("- ") || l.text == "-" {
            return Err(ParseError {
                line: l.no,
                reason: "block sequences ('- item') are not supported; use [a, b, ...]".into(),
            });
        }
        let (key, rest) = l.text.split_once(':').ok_or_else(|| ParseError {
            line: l.no,
            reason: format!("expected 'key: value', found '{}'", l.text),
        })?;
        let key = unquote(key);
        if !keys.insert(key.clone()) {
            return Err(ParseError {
                line: l.no,
                reason: format!("duplicate key '{key}'"),
            });
        }
        let rest = strip_tag(rest);
        let start_line = l.no;
        *pos += 1;
        let node = if rest.is_empty() {
            match lines.get(*pos) {
                Some(next) if next.indent > indent => {
                    let child_indent = next.indent;
                    parse_map(lines, pos, child_indent, depth + 1)?
                }
                _ => Node::Scalar(String::new()),
            }
        } else if rest.starts_with('[') || rest.starts_with('{') {
            // A flow collection may continue over the following lines.
            // The balance is kept as lines are added (counting the whole text again
            // on every line would be quadratic in an unterminated collection).
            let mut text = rest.to_string();
            let mut balance = bracket_balance(&text);
            while balance > 0 {
                let Some(next) = lines.get(*pos) else {
                    return Err(ParseError {
                        line: start_line,
                        reason: format!("unterminated flow collection for '{key}'"),
                    });
                };
                text.push(' ');
                text.push_str(next.text);
                balance += bracket_balance(next.text);
                *pos += 1;
            }
            parse_flow(&text, start_line, depth + 1)?
        } else {
            Node::Scalar(unquote(rest))
        };
        entries.push((key, node));
    }
    Ok(Node::Map(entries))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deep_nesting_is_an_error_not_a_stack_overflow() {
        let mut doc = String::new();
        for i in 0..100_000 {
            doc.push_str(&" ".repeat(i.min(200_000)));
            doc.push_str("k:\n");
            if i > 2000 {
                break;
            }
        }
        let e = parse(&doc).unwrap_err();
        assert!(e.reason.contains("deeper"), "{e:?}");
        let flow = format!("k: {}1{}\n", "{a: ".repeat(50_000), "}".repeat(50_000));
        let e = parse(&flow).unwrap_err();
        assert!(e.reason.contains("deeper"), "{e:?}");
    }

    #[test]
    fn an_unterminated_list_over_many_lines_is_one_linear_pass() {
        // 200 k lines after an unterminated '[': counted once each (the old count of
        // the whole text per line took minutes here).
        let mut doc = String::from("data: [\n");
        for _ in 0..200_000 {
            doc.push_str("  1.0,\n");
        }
        let e = parse(&doc).unwrap_err();
        assert!(e.reason.contains("unterminated"), "{e:?}");
        assert_eq!(e.line, 1);
        // As many distinct keys: the duplicate check is not quadratic either.
        let keys: String = (0..200_000).map(|i| format!("k{i}: 1\n")).collect();
        assert!(parse(&keys).is_ok());
    }

    #[test]
    fn parses_opencv_and_ros_shapes() {
        let doc = "%YAML:1.0\n---\nimage_width: 640 # px\nname: \"a # b\"\nK: !!opencv-matrix\n   rows: 3\n   data: [ 1., 2.,\n       3. ]\nD: {rows: 1, data: [0.1, 0.2]}\n";
        let n = parse(doc).unwrap();
        assert_eq!(n.get("image_width"), Some(&Node::Scalar("640".into())));
        assert_eq!(n.get("name"), Some(&Node::Scalar("a # b".into())));
        let k = n.get("K").unwrap();
        assert_eq!(k.get("rows"), Some(&Node::Scalar("3".into())));
        assert_eq!(
            k.get("data"),
            Some(&Node::Seq(vec!["1.".into(), "2.".into(), "3.".into()]))
        );
        let d = n.get("D").unwrap();
        assert_eq!(
            d.get("data"),
            Some(&Node::Seq(vec!["0.1".into(), "0.2".into()]))
        );
    }

    #[test]
    fn errors_carry_line_numbers() {
        let e = parse("a: 1\nb: [1, 2\n").unwrap_err();
        assert_eq!(e.line, 2);
        let e = parse("a: 1\n  b: 2\n").unwrap_err();
        assert_eq!(e.line, 2);
        let e = parse("a: 1\njunk\n").unwrap_err();
        assert_eq!(e.line, 2);
        let e = parse("a:\n  - 1\n").unwrap_err();
        assert_eq!(e.line, 2);
    }
}
