//! Topic patterns: the `record:` lists of graph files, `--topics` filters, diff tolerances.

/// Whether `text` matches `pattern`, where `*` matches any run of characters (`/` included)
/// and every other character itself.
pub fn glob_matches(pattern: &str, text: &str) -> bool {
    let pattern: Vec<char> = pattern.chars().collect();
    let text: Vec<char> = text.chars().collect();
    let (mut p, mut t) = (0, 0);
    // Where the last `*` was and the text position it is currently stretched to.
    let mut star: Option<(usize, usize)> = None;
    while t < text.len() {
        match pattern.get(p) {
            Some('*') => {
                star = Some((p, t));
                p += 1;
            }
            Some(&c) if c == text[t] => {
                p += 1;
                t += 1;
            }
            _ => match star {
                Some((star_p, star_t)) => {
                    star = Some((star_p, star_t + 1));
                    p = star_p + 1;
                    t = star_t + 1;
                }
                None => return false,
            },
        }
    }
    pattern[p..].iter().all(|&c| c == '*')
}

#[cfg(test)]
mod tests {
    use super::glob_matches;

    #[test]
    fn glob_patterns() {
        for (pattern, text, expected) in [
            ("*", "", true),
            ("*", "a/b", true),
            ("a/*", "a/b/c", true),
            ("*/trace", "dsp/trace", true),
            ("*/trace", "dsp/traces", false),
            ("d*p/*e", "dsp/trace", true),
            ("dsp", "dsp", true),
            ("dsp", "dsp2", false),
            ("", "", true),
            ("", "a", false),
            ("**a", "bba", true),
            ("a*b*c", "abxbxc", true),
            ("a*b*c", "abxbxd", false),
        ] {
            assert_eq!(glob_matches(pattern, text), expected, "{pattern:?} on {text:?}");
        }
    }
}
