// The parameter form, generated from the API's own parameter spec: the `Params` schema of
// /openapi.json (proto/openapi.yaml). Every field shows its default; the page does not validate,
// it sends what the user changed and shows the server's 422 text.

const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);

function types(prop) {
  if (prop.oneOf) return prop.oneOf.flatMap(types);
  return Array.isArray(prop.type) ? prop.type : [prop.type];
}

/** The fields a LiDAR user sets, shown first; every other field folds under "Advanced". */
export const MAIN = ['method', 'knn', 'max_move', 'classes', 'outliers'];

/** Builds the inputs into `fieldset`; returns { values(), reset(), fields }. */
export function buildForm(fieldset, schema) {
  const fields = [];
  // The spec's properties arrive sorted by name; the main ones come first, in MAIN's order, then
  // the method's presets.
  const first = [...MAIN, 'paper', 'iterations', 'rings', 'outlier_alpha'];
  const rank = (n) => (first.includes(n) ? first.indexOf(n) : first.length);
  const entries = Object.entries(schema.properties).sort(([a], [b]) => rank(a) - rank(b) || a.localeCompare(b));
  const advanced = document.createElement('details');
  advanced.className = 'advanced';
  const summary = document.createElement('summary');
  summary.textContent = `Advanced (${entries.filter(([n]) => !MAIN.includes(n)).length} more)`;
  const more = document.createElement('div');
  more.className = 'fields';
  advanced.append(summary, more);
  for (const [name, prop] of entries) {
    const t = types(prop);
    const nullable = t.includes('null');
    const label = document.createElement('label');
    const id = `p-${name}`;
    label.htmlFor = id;
    const help = [prop.description, defaultText(prop, nullable), rangeText(prop)].filter(Boolean).join(' · ');
    let input;
    if (prop.enum) {
      input = document.createElement('select');
      for (const v of prop.enum) input.append(new Option(String(v), String(v)));
    } else if (t.includes('string')) {
      input = document.createElement('input');
      input.type = 'text';
      if (nullable && prop.default === undefined) input.placeholder = 'auto';
    } else if (t.includes('boolean')) {
      input = document.createElement('input');
      input.type = 'checkbox';
      label.classList.add('check');
    } else {
      input = document.createElement('input');
      input.type = 'number';
      input.step = t.includes('integer') ? '1' : 'any';
      if (nullable && prop.default === undefined) input.placeholder = 'auto';
    }
    input.id = id;
    input.name = name;
    input.dataset.param = name;
    if (input.type === 'checkbox') {
      label.append(input, document.createTextNode(name));
    } else {
      label.append(document.createTextNode(name), input);
    }
    if (help) {
      const h = document.createElement('span');
      h.className = 'help';
      h.innerHTML = esc(help);
      label.append(h);
    }
    (MAIN.includes(name) ? fieldset : more).append(label);
    fields.push({ name, prop, input, nullable });
  }
  fieldset.append(advanced);
  const reset = () => {
    for (const f of fields) {
      if (f.input.type === 'checkbox') f.input.checked = f.prop.default === true;
      else if (f.prop.default !== undefined && f.prop.default !== null) f.input.value = String(f.prop.default);
      else f.input.value = '';
    }
  };
  reset();
  // Only what differs from the spec's default is sent, so the server's own rules for unset
  // fields (e.g. bilateral's three iterations) apply.
  const values = () => {
    const out = {};
    for (const f of fields) {
      const { name, prop, input } = f;
      if (input.type === 'checkbox') {
        if (input.checked !== (prop.default === true)) out[name] = input.checked;
      } else if (input.tagName === 'SELECT') {
        if (input.value !== String(prop.default)) out[name] = input.value;
      } else {
        const raw = input.value.trim();
        if (raw === '' && input.validity.badInput) out[name] = input.validationMessage || 'not a number';
        else if (raw === '') continue;
        else if (raw !== String(prop.default)) out[name] = input.type === 'text' ? raw : Number(raw);
      }
    }
    return out;
  };
  return { fields, reset, values };
}

function defaultText(prop, nullable) {
  if (prop.default !== undefined) return `default ${JSON.stringify(prop.default)}`;
  return nullable ? 'default: auto' : '';
}

function rangeText(prop) {
  const lo = prop.minimum ?? prop.exclusiveMinimum;
  const hi = prop.maximum ?? prop.exclusiveMaximum;
  if (lo === undefined && hi === undefined) return '';
  const l = lo === undefined ? '' : `${prop.exclusiveMinimum !== undefined ? '>' : '≥'} ${lo}`;
  const h = hi === undefined ? '' : `${prop.exclusiveMaximum !== undefined ? '<' : '≤'} ${hi}`;
  return [l, h].filter(Boolean).join(', ');
}
