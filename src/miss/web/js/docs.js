// Swagger UI for /openapi.json. The bundle comes from npm (swagger-ui-dist) and is served
// by MISS itself: no CDN, and no inline script, so the page runs under the same strict
// Content-Security-Policy as every other page.
/* global SwaggerUIBundle */
window.ui = SwaggerUIBundle( {
	url: '/openapi.json',
	dom_id: '#swagger-ui',
	deepLinking: true,
	presets: [ SwaggerUIBundle.presets.apis ],
	layout: 'BaseLayout',
} );
document.body.dataset.ready = '1';
