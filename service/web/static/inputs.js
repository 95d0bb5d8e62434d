// The form's inputs for the generation parameters, made from the list /web/config.json states (one entry per
// field of fastmesh.params.GenerateParams: name, type, choices, help): plain functions, no DOM, so that they run
// (and are tested) without a browser as well as in the page.

const escape = (s) => String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);

// The parameters the page shows as values (numbers and choices) and as checkboxes (bools), in that order.
export function valueParams(params) { return params.filter((p) => p.type !== 'bool').map((p) => p.name); }
export function flagParams(params) { return params.filter((p) => p.type === 'bool').map((p) => p.name); }

// One parameter's labelled input: a number box (int, float), a select (choice) or a checkbox (bool).
export function inputHtml(p) {
  const name = escape(p.name);
  const title = p.help ? ` title="${escape(p.help)}"` : '';
  if (p.type === 'bool') return `<label class="check"${title}><input name="${name}" type="checkbox"> ${name}</label>`;
  if (p.type === 'choice') {
    const options = p.choices.map((c) => `<option value="${escape(c)}">${escape(c)}</option>`).join('');
    return `<label${title}>${name} <select name="${name}">${options}</select></label>`;
  }
  const step = p.type === 'int' ? '1' : 'any';
  return `<label${title}>${name} <input name="${name}" type="number" step="${step}"></label>`;
}

// Every parameter's input, values first and checkboxes after.
export function inputsHtml(params) {
  const ordered = [...params.filter((p) => p.type !== 'bool'), ...params.filter((p) => p.type === 'bool')];
  return ordered.map(inputHtml).join('\n');
}
