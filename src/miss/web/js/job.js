// How a model job's progress is shown, shared by the volume page and the viewer.

import { el, formatCount } from './format.js';

// The pipeline's stages in order, with words a physician reads.
export const STAGES = [
	[ 'queued', 'Waiting for a worker' ],
	[ 'preview', 'Preview' ],
	[ 'surface', 'Marching cubes' ],
	[ 'decimate', 'Decimation' ],
	[ 'check', 'Checking the error bound' ],
	[ 'lod', 'Levels of detail' ],
	[ 'write', 'Writing files' ],
	[ 'measure', 'Measuring the error' ],
	[ 'done', 'Done' ],
];

// Moments of a job that are not steps of the list above.
const OTHER_STAGES = { starting: 'Starting', read: 'Reading the scan', store: 'Saving the model' };

export function stageLabel( stage ) {
	const known = STAGES.find( ( [ key ] ) => key === stage );
	return known ? known[ 1 ] : OTHER_STAGES[ stage ] || stage || 'Starting';
}

// Fills a list with the stages, marking the ones passed and the current one.
// A stage the pipeline adds later (say 'read') is simply shown as text above.
export function renderStages( list, model ) {
	const stage = model.status === 'queued' ? 'queued' : model.status === 'done' ? 'done' : model.stage;
	const at = STAGES.findIndex( ( [ key ] ) => key === stage );
	list.replaceChildren( ...STAGES.map( ( [ key, label ], i ) => {
		const state = model.status === 'done' || ( at >= 0 && i < at ) ? 'done' : i === at ? 'active' : '';
		return el( `li${state ? '.' + state : ''}`, { dataset: { stage: key } }, label );
	} ) );
}

export function percent( model ) {
	return `${Math.round( ( model.progress || 0 ) * 100 )} %`;
}

// A model's parameters in a line: "level 300 · rate 2 · quadric · 2 parts".
export function describeModel( m ) {
	const p = m.params || {};
	const sr = Array.isArray( p.sample_rate ) ? p.sample_rate.join( ',' ) : p.sample_rate;
	const thresholds = p.parts ? p.parts.filter( ( x ) => x.level != null ).map( ( x ) => x.level ) : p.levels || [ p.level ];
	let levels = thresholds.length > 1 ? `levels ${thresholds.join( ', ' )}` : `level ${thresholds[ 0 ]}`;
	if ( p.labels != null ) levels = `labels ${p.labels === 'all' ? 'all' : p.labels.join( ', ' )}`;
	const n = m.stats?.parts?.length;
	const parts = n ? ` · ${formatCount( n )} part${n === 1 ? '' : 's'}` : '';
	return `${levels}${p.components && p.components !== 'all' ? ` · ${p.components}` : ''} · rate ${sr} · ${p.decimate}${parts}`;
}

// The name its owner gave the model, else its parameters.
export function modelTitle( m ) {
	return m.name || describeModel( m );
}
